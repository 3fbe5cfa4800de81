// BLAKE2s (RFC 7693), keyed, for the page's MACs: crypto.subtle is missing outside a secure
// context (a page served as http://192.168.x.y), and the pairing token must never travel.
// The browser test checks it against Python's hashlib.blake2s.
"use strict";

const BLAKE2S_IV = new Uint32Array([
  0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a,
  0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19]);
const BLAKE2S_SIGMA = [
  [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15],
  [14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3],
  [11, 8, 12, 0, 5, 2, 15, 13, 10, 14, 3, 6, 7, 1, 9, 4],
  [7, 9, 3, 1, 13, 12, 11, 14, 2, 6, 5, 10, 4, 0, 15, 8],
  [9, 0, 5, 7, 2, 4, 10, 15, 14, 1, 11, 12, 6, 8, 3, 13],
  [2, 12, 6, 10, 0, 11, 8, 3, 4, 13, 7, 5, 15, 14, 1, 9],
  [12, 5, 1, 15, 14, 13, 4, 10, 0, 7, 6, 3, 9, 2, 8, 11],
  [13, 11, 7, 14, 12, 1, 3, 9, 5, 0, 15, 4, 8, 6, 2, 10],
  [6, 15, 14, 9, 11, 3, 0, 8, 12, 2, 13, 7, 1, 4, 10, 5],
  [10, 2, 8, 4, 7, 6, 1, 5, 15, 11, 9, 14, 3, 12, 13, 0]];

function blake2sCompress(h, m, t, last) {
  const v = new Uint32Array(16);
  v.set(h);
  v.set(BLAKE2S_IV, 8);
  v[12] ^= t;
  v[13] ^= Math.floor(t / 0x100000000);
  if (last) v[14] = ~v[14];
  const rotr = (x, n) => (x >>> n) | (x << (32 - n));
  const g = (a, b, c, d, x, y) => {
    v[a] = v[a] + v[b] + x; v[d] = rotr(v[d] ^ v[a], 16);
    v[c] = v[c] + v[d]; v[b] = rotr(v[b] ^ v[c], 12);
    v[a] = v[a] + v[b] + y; v[d] = rotr(v[d] ^ v[a], 8);
    v[c] = v[c] + v[d]; v[b] = rotr(v[b] ^ v[c], 7);
  };
  for (let r = 0; r < 10; r++) {
    const s = BLAKE2S_SIGMA[r];
    g(0, 4, 8, 12, m[s[0]], m[s[1]]); g(1, 5, 9, 13, m[s[2]], m[s[3]]);
    g(2, 6, 10, 14, m[s[4]], m[s[5]]); g(3, 7, 11, 15, m[s[6]], m[s[7]]);
    g(0, 5, 10, 15, m[s[8]], m[s[9]]); g(1, 6, 11, 12, m[s[10]], m[s[11]]);
    g(2, 7, 8, 13, m[s[12]], m[s[13]]); g(3, 4, 9, 14, m[s[14]], m[s[15]]);
  }
  for (let i = 0; i < 8; i++) h[i] ^= v[i] ^ v[i + 8];
}

// blake2s(key: Uint8Array (0..32 bytes), data: Uint8Array, outlen 1..32) -> Uint8Array
function blake2s(key, data, outlen) {
  const h = new Uint32Array(BLAKE2S_IV);
  h[0] ^= 0x01010000 ^ (key.length << 8) ^ outlen;
  let msg = data;
  if (key.length) {  // the key, padded to a block, is the first block
    msg = new Uint8Array(64 + data.length);
    msg.set(key);
    msg.set(data, 64);
  }
  const blocks = Math.max(1, Math.ceil(msg.length / 64));
  const m = new Uint32Array(16);
  const block = new Uint8Array(64);
  for (let i = 0; i < blocks; i++) {
    const last = i === blocks - 1;
    block.fill(0);
    block.set(msg.subarray(i * 64, Math.min(msg.length, i * 64 + 64)));
    for (let j = 0; j < 16; j++) {
      m[j] = block[4 * j] | (block[4 * j + 1] << 8) | (block[4 * j + 2] << 16) |
        (block[4 * j + 3] << 24);
    }
    blake2sCompress(h, m, last ? msg.length : (i + 1) * 64, last);
  }
  const out = new Uint8Array(outlen);
  for (let i = 0; i < outlen; i++) out[i] = (h[i >> 2] >>> (8 * (i & 3))) & 0xff;
  return out;
}

function bytesToHex(bytes) {
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

function hexToBytes(hex) {
  const out = new Uint8Array(hex.length >> 1);
  for (let i = 0; i < out.length; i++) out[i] = parseInt(hex.substr(2 * i, 2), 16);
  return out;
}
