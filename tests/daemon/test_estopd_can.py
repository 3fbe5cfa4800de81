"""estopd --can against a fake SocketCAN (this kernel has none; the real bus is tested under
vcan by the HIL harness).

An LD_PRELOAD shim, compiled here from the C source below, turns the daemon's AF_CAN raw
socket into an AF_UNIX datagram socket: frames it sends arrive, as struct can_frame, on a
socket this test reads (the "bus"), the test can send it CAN error frames, and a control file
makes its writes fail (ENOBUFS, ENETDOWN, ENXIO) or its interface vanish. That exercises the
daemon's own logic: retry, fault, recovery, reopen, error-frame logging, the last frame.
"""

from __future__ import annotations

import signal
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from daemon_util import (
    ARMED,
    BRAKE_ID,
    R_BOOT,
    R_FAULT,
    STATUS_ID,
    STOPPED,
    Daemon,
    Frame,
    build_preload_shim,
    check_frames,
    first_new_match,
    udp_packet,
)

pytestmark = [pytest.mark.timeout(60), pytest.mark.timing]

SHIM_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#define PF_CAN_ 29
#define SOL_CAN_RAW_ 101
static int fake[64];

static int is_fake(int fd) { return fd >= 0 && fd < 64 && fake[fd]; }

static void mode(char *buf, size_t n) {
    char path[200];
    ssize_t r;
    int fd;
    snprintf(path, sizeof path, "%s/mode", getenv("FAKECAN_DIR"));
    buf[0] = 0;
    fd = open(path, O_RDONLY);
    if (fd < 0) return;
    r = read(fd, buf, n - 1);
    close(fd);
    buf[r > 0 ? r : 0] = 0;
}

static void unaddr(struct sockaddr_un *a, const char *name) {
    memset(a, 0, sizeof *a);
    a->sun_family = AF_UNIX;
    snprintf(a->sun_path, sizeof a->sun_path, "%s/%s", getenv("FAKECAN_DIR"), name);
}

int socket(int domain, int type, int protocol) {
    static int (*real)(int, int, int);
    int fd;
    if (!real) real = (int (*)(int, int, int))dlsym(RTLD_NEXT, "socket");
    if (domain != PF_CAN_) return real(domain, type, protocol);
    fd = real(AF_UNIX, SOCK_DGRAM | (type & (SOCK_NONBLOCK | SOCK_CLOEXEC)), 0);
    if (fd >= 0 && fd < 64) fake[fd] = 1;
    return fd;
}

int setsockopt(int fd, int level, int name, const void *v, socklen_t len) {
    static int (*real)(int, int, int, const void *, socklen_t);
    if (!real)
        real = (int (*)(int, int, int, const void *, socklen_t))dlsym(RTLD_NEXT, "setsockopt");
    if (is_fake(fd) && level == SOL_CAN_RAW_) return 0;
    return real(fd, level, name, v, len);
}

int bind(int fd, const struct sockaddr *a, socklen_t len) {
    static int (*real)(int, const struct sockaddr *, socklen_t);
    struct sockaddr_un dev, bus;
    if (!real) real = (int (*)(int, const struct sockaddr *, socklen_t))dlsym(RTLD_NEXT, "bind");
    if (!is_fake(fd)) return real(fd, a, len);
    unaddr(&dev, "dev");
    unaddr(&bus, "bus");
    unlink(dev.sun_path);
    if (real(fd, (struct sockaddr *)&dev, sizeof dev) != 0) return -1;
    return connect(fd, (struct sockaddr *)&bus, sizeof bus);
}

unsigned if_nametoindex(const char *name) {
    char m[32];
    (void)name;
    mode(m, sizeof m);
    if (strncmp(m, "gone", 4) == 0) { errno = ENODEV; return 0; }
    return 7;
}

int close(int fd) {
    static int (*real)(int);
    if (!real) real = (int (*)(int))dlsym(RTLD_NEXT, "close");
    if (fd >= 0 && fd < 64) fake[fd] = 0;
    return real(fd);
}

ssize_t write(int fd, const void *buf, size_t n) {
    static ssize_t (*real)(int, const void *, size_t);
    char m[32];
    if (!real) real = (ssize_t (*)(int, const void *, size_t))dlsym(RTLD_NEXT, "write");
    if (!is_fake(fd)) return real(fd, buf, n);
    mode(m, sizeof m);
    if (strncmp(m, "enobufs", 7) == 0) { errno = ENOBUFS; return -1; }
    if (strncmp(m, "enetdown", 8) == 0) { errno = ENETDOWN; return -1; }
    if (strncmp(m, "enxio", 5) == 0 || strncmp(m, "gone", 4) == 0) { errno = ENXIO; return -1; }
    return real(fd, buf, n);
}
"""

CAN_ERR_FLAG = 0x20000000
CAN_ERR_CRTL = 0x04
CAN_ERR_BUSOFF = 0x40


@pytest.fixture(scope="module")
def shim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fakecan")
    (d / "fakecan.c").write_text(SHIM_C)
    return build_preload_shim(d / "fakecan.c", d)


class Bus:
    """The far end of the fake CAN socket: collects frames, sends error frames."""

    def __init__(self, path: Path) -> None:
        self.dir = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path / "bus"))
        self.sock.settimeout(0.05)
        self.frames: list[Frame] = []
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                raw = self.sock.recv(64)
            except TimeoutError:
                continue
            except OSError:
                return
            can_id, dlc, data = struct.unpack("<IB3x8s", raw)
            self.frames.append(Frame(time.time(), "bus", can_id, data[:dlc]))

    def set_mode(self, mode: str) -> None:
        (self.dir / "mode").write_text(mode)

    def send_error(self, can_id: int, data: bytes) -> None:
        self.sock.sendto(struct.pack("<IB3x8s", CAN_ERR_FLAG | can_id, 8, data),
                         str(self.dir / "dev"))

    def wait(self, pred: Callable[[Frame], bool], timeout: float = 3.0,
             after: int = 0) -> Frame:
        return first_new_match(lambda: self.frames, pred, after, timeout, "frame on the fake bus")

    def close(self) -> None:
        self._stop.set()
        self._th.join(timeout=5)
        self.sock.close()


class CanDaemon(Daemon):
    def __init__(self, tmp_path: Path, shim: Path, *extra: str) -> None:
        super().__init__(tmp_path, *extra)
        i = self.argv.index("--can-log")
        del self.argv[i:i + 2]  # the base class's default; `extra` may set it again
        self.argv += ["--can", "vcan0"]
        self.env = {"LD_PRELOAD": str(shim), "FAKECAN_DIR": str(tmp_path)}


@pytest.fixture
def rig(tmp_path: Path, shim: Path) -> Iterator[tuple[CanDaemon, Bus]]:
    bus = Bus(tmp_path)
    bus.set_mode("ok")
    d = CanDaemon(tmp_path, shim)
    try:
        d.start()
        yield d, bus
    finally:
        d.kill()
        bus.close()


def _keepalive(d: Daemon, stop: threading.Event) -> None:
    while not stop.is_set():
        d.send_udp(udp_packet())
        stop.wait(0.02)


def test_frames_go_to_the_bus(rig: tuple[CanDaemon, Bus]) -> None:
    d, bus = rig
    assert "can=vcan0" in d.start_line and "can_log=off" in d.start_line
    bus.wait(lambda f: f.can_id == STATUS_ID and f.counter == 2)
    frames = list(bus.frames)
    check_frames(frames)
    assert frames[0].can_id == BRAKE_ID and frames[0].data.hex().upper() == "016400010000009C"
    assert d.frames() == []  # no can-log unless asked for


def test_can_log_names_the_interface(tmp_path: Path, shim: Path) -> None:
    bus = Bus(tmp_path)
    bus.set_mode("ok")
    try:
        with CanDaemon(tmp_path, shim, "--can-log", "-") as d:
            bus.wait(lambda f: f.can_id == STATUS_ID and f.counter == 1)
            logged = d.frames()
        assert logged and all(f.iface == "vcan0" for f in logged)
        check_frames(logged)
        assert [f.data for f in logged[:10]] == [f.data for f in bus.frames[:10]]
    finally:
        bus.close()


@pytest.mark.parametrize(("mode", "err"), [("enobufs", "ENOBUFS"), ("enetdown", "ENETDOWN")])
def test_failing_sends_fault_then_recover(rig: tuple[CanDaemon, Bus], mode: str,
                                          err: str) -> None:
    d, bus = rig
    stop = threading.Event()
    th = threading.Thread(target=_keepalive, args=(d, stop), daemon=True)
    th.start()
    try:
        d.arm()
        bus.wait(lambda f: f.can_id == BRAKE_ID and f.state == ARMED)
        bus.set_mode(mode)
        failed_at = time.monotonic()
        d.wait_log(lambda s: "can_error" in s and "what=tx_failed" in s and f"err={err}" in s)
        d.wait_log(lambda s: " fault " in s and "cause=can_tx" in s)
        d.wait_log(lambda s: "state ARMED->STOPPED reason=fault src=-" in s)
        assert time.monotonic() - failed_at < 1.0
        n = len(bus.frames)
        bus.set_mode("ok")
        d.wait_log(lambda s: "can_recovered" in s)
        # Braking resumes at once, latched STOPPED for the fault while packets keep coming.
        f = bus.wait(lambda f: f.can_id == BRAKE_ID, after=n)
        assert (f.state, f.reason, f.data[0]) == (STOPPED, R_FAULT, 1)
        time.sleep(0.05)
        assert all(x.state == STOPPED for x in bus.frames[n:] if x.can_id == BRAKE_ID)
    finally:
        stop.set()
        th.join(timeout=5)
    # one log line per failure episode, not one per retry
    assert sum("what=tx_failed" in s for s in d.log()) == 1
    for fr in bus.frames:
        assert fr.crc_ok()


def test_short_outage_recovers_at_once(rig: tuple[CanDaemon, Bus]) -> None:
    d, bus = rig
    bus.set_mode("enobufs")
    d.wait_log(lambda s: "what=tx_failed" in s)
    n = len(bus.frames)
    ok_at = time.time()
    bus.set_mode("ok")
    d.wait_log(lambda s: "can_recovered" in s)
    first = bus.wait(lambda f: f.can_id == BRAKE_ID, after=n)
    assert first.t - ok_at < 0.05
    assert first.state == STOPPED and first.data[0] == 1
    for f in bus.frames:
        assert f.crc_ok()


def test_interface_gone_and_back(rig: tuple[CanDaemon, Bus]) -> None:
    d, bus = rig
    bus.set_mode("gone")
    d.wait_log(lambda s: "what=tx_failed" in s and "err=ENXIO" in s)
    d.wait_log(lambda s: "cause=can_tx" in s)
    time.sleep(0.25)  # a few reopen attempts while it is still gone
    n = len(bus.frames)
    bus.set_mode("ok")
    d.wait_log(lambda s: "can_reopened" in s)
    f = bus.wait(lambda f: f.can_id == BRAKE_ID, after=n)
    assert f.state == STOPPED and f.reason == R_BOOT  # a fault while STOPPED keeps the reason
    assert d.proc is not None and d.proc.poll() is None


def test_error_frames_are_logged_bus_off_stops(rig: tuple[CanDaemon, Bus]) -> None:
    d, bus = rig
    stop = threading.Event()
    th = threading.Thread(target=_keepalive, args=(d, stop), daemon=True)
    th.start()
    try:
        d.arm()
        bus.send_error(CAN_ERR_CRTL, bytes([0, 0x20, 0, 0, 0, 0, 0, 0]))
        d.wait_log(lambda s: "what=error_passive_tx" in s)
        time.sleep(0.05)
        assert not any("ARMED->STOPPED" in s for s in d.log())  # error-passive: log only
        bus.send_error(CAN_ERR_BUSOFF, bytes(8))
        d.wait_log(lambda s: "what=bus_off" in s)
        d.wait_log(lambda s: "cause=can_bus_off" in s)
        d.wait_log(lambda s: "state ARMED->STOPPED reason=fault" in s)
    finally:
        stop.set()
        th.join(timeout=5)


def test_sigterm_last_frame_on_the_bus(rig: tuple[CanDaemon, Bus]) -> None:
    d, bus = rig
    d.arm()
    assert d.signal(signal.SIGTERM) == 0
    time.sleep(0.1)
    last = bus.frames[-1]
    assert (last.can_id, last.data[0], last.state, last.reason) == (BRAKE_ID, 1, STOPPED,
                                                                     R_FAULT)
    check_frames(list(bus.frames))
