/*
 * estop_core: the portable emergency-stop state machine (PROTOCOL.md sections 1-4).
 *
 * Portable C99. All state lives in a caller-owned estop_core_t; there is no heap, no mutable
 * global, no I/O, no clock read and no randomness: time comes in as a wrapping uint32
 * microsecond tick, the key and the session (PROTOCOL.md 5) with the configuration.
 *
 * Host contract:
 *  - Call estop_init() once, then estop_tick() at once (the boot frames are due at init time).
 *  - Every entry point takes the current tick `now_us` and fills a caller-owned estop_out_t:
 *    CAN frames to send (in order), at most one TCP reply, a "close this slot" request, a
 *    state-change event, and out->next_call_us: the host must call again (estop_tick at the
 *    latest) when the tick reaches that value.
 *  - Successive calls may be at most ESTOP_MAX_STEP_US apart. A host that keeps a wider clock
 *    feeds longer gaps in steps of at most that size. A step that looks longer (the tick went
 *    backwards) is treated as an internal fault: the unit stops.
 *  - TCP bytes are consumed at most one frame per call: call estop_tcp_rx() again with the
 *    rest until everything is consumed, so the reply buffer is never more than one frame.
 *    A frame's first 4 bytes decide its length: "ESQ2" starts a 48-byte request frame
 *    (answered by a 48-byte reply), anything else a 16-byte plain frame (16-byte reply).
 *  - With a key (cfg.key_len 32), only authenticated control packets (60 bytes) keep the unit
 *    alive and only an authenticated RELEASE (48-byte request frame) releases it; anyone may
 *    stop (plain STOP or LIFT, request frame, stop or lift datagram, whatever its tag).
 *    Without a key, plain control packets keep it alive and RELEASE is plain; a
 *    request-frame RELEASE gets NAK 4.
 *  - Silence is answered in two stages (PROTOCOL.md 3): SLOWING at the slow time S (left
 *    again after ESTOP_REARM_PACKETS valid packets), STOPPED at the timeout T. Each happens
 *    at its deadline: next_call_us names it. A call that comes late past both goes straight
 *    to STOPPED.
 */
#ifndef ESTOP_CORE_H
#define ESTOP_CORE_H

#include <stddef.h>
#include <stdint.h>

#include "estop_blake2s.h"

#ifdef __cplusplus
extern "C" {
#endif

#define ESTOP_VERSION_MAJOR 3u
#define ESTOP_VERSION_MINOR 0u

/* Wire sizes (PROTOCOL.md 1, 2, 4). */
#define ESTOP_UDP_LEN 20u
#define ESTOP_UDP_LEN_NO_HORN 16u
#define ESTOP_TCP_FRAME_LEN 16u
#define ESTOP_REQ_FRAME_LEN 48u        /* request frame of PROTOCOL.md 5.2 (also the stop datagram) */
#define ESTOP_REPLY_MAX 48u            /* reply frame of PROTOCOL.md 5.3; plain replies are 16 */
#define ESTOP_UDP_AUTH_LEN 60u         /* authenticated control packet of PROTOCOL.md 5.1 */
#define ESTOP_MAGIC_REQUEST 0x32515345u /* "ESQ2" read as a little-endian u32 */
#define ESTOP_MAGIC_CONTROL 0x32555345u /* "ESU2" */
#define ESTOP_MAGIC_REPLY 0x32525345u   /* "ESR2" */
#define ESTOP_KEY_LEN 32u
#define ESTOP_TAG_LEN 16u
/* Remote ids the unit keeps counters for in one session (PROTOCOL.md 5). */
#define ESTOP_MAX_REMOTES 8u
/* Bins of the histogram of gaps between consecutive valid control packets (docs/LINK.md):
 * bin 0 below 1.024 ms, bins 1..30 half-octaves from 1.024 ms to 33.5 s, bin 31 above. */
#define ESTOP_GAP_BINS 32u
#define ESTOP_CAN_DLC 8u

/* TCP message ids and reply codes (PROTOCOL.md 2). */
#define ESTOP_MSG_STATUS 0x00000001u
#define ESTOP_MSG_RELEASE 0x00000002u
#define ESTOP_MSG_LIFT 0x00000003u     /* the operator let go of the dead-man switch: a stop */
#define ESTOP_MSG_ACK 0x00000080u
#define ESTOP_MSG_NAK 0x00000081u
#define ESTOP_NAK_NONE 0u
#define ESTOP_NAK_UNKNOWN_ID 1u
#define ESTOP_NAK_NO_LIVE_LINK 2u
#define ESTOP_NAK_NOT_NEUTRAL 3u
#define ESTOP_NAK_NOT_AUTHENTICATED 4u

/* States, reasons, flags (PROTOCOL.md 3). */
#define ESTOP_STATE_STOPPED 0u
#define ESTOP_STATE_ARMED 1u
#define ESTOP_STATE_SLOWING 2u        /* controlled stop while the link is silent; not latched */
#define ESTOP_STATE_COUNT 3u
#define ESTOP_REASON_NONE 0u
#define ESTOP_REASON_BOOT 1u
#define ESTOP_REASON_TCP_STOP 2u
#define ESTOP_REASON_UDP_TIMEOUT 3u
#define ESTOP_REASON_FAULT 4u
#define ESTOP_REASON_LIFT 5u
#define ESTOP_REASON_COUNT 6u
#define ESTOP_FLAG_LINK_DEGRADED 0x01u

/* ESTOP_BRAKE byte 0, brake_request (PROTOCOL.md 4). */
#define ESTOP_BRAKE_RELEASE 0u        /* ARMED */
#define ESTOP_BRAKE_EMERGENCY 1u      /* STOPPED */
#define ESTOP_BRAKE_CONTROLLED 2u     /* SLOWING, at the slow level */
#define ESTOP_BRAKE_LEVEL_FULL 100u
/* Valid control packets since SLOWING began that bring the unit back to ARMED. */
#define ESTOP_REARM_PACKETS 3u

/* Longest gap between two calls; longer gaps must be fed in steps. */
#define ESTOP_MAX_STEP_US 0x7FFFFFFFu
/* TCP connection slots the core can track at once (the spec asks for at least 4). */
#define ESTOP_MAX_SLOTS 8u
/* At most: one state-change brake frame from the clock, one status frame, one state-change
 * brake frame from the input. */
#define ESTOP_OUT_MAX_CAN 3u

/* Defaults (PROTOCOL.md). */
#define ESTOP_DEFAULT_TIMEOUT_US 200000u
#define ESTOP_DEFAULT_SLOW_LEVEL 30u   /* percent of the emergency deceleration */
#define ESTOP_DEFAULT_STOP_ID 0xE570E570u
#define ESTOP_DEFAULT_BRAKE_CAN_ID 0x050u
#define ESTOP_DEFAULT_STATUS_CAN_ID 0x051u
#define ESTOP_DEFAULT_BRAKE_DATA_ID 0x0E57u
#define ESTOP_DEFAULT_STATUS_DATA_ID 0x0E58u
#define ESTOP_DEFAULT_RELEASE_PACKETS 5u
#define ESTOP_DEFAULT_BRAKE_PERIOD_US 10000u
#define ESTOP_DEFAULT_STATUS_PERIOD_US 100000u
/* Tag checks of authenticated control packets (PROTOCOL.md 5, "a bounded cost"): each remote
 * id with a place (for its next counters), and everything else together, get this many per
 * window. ESTOP_TAG_CHECKS_ALL (0): no budget, every tag is checked (a host with the CPU for
 * it, such as estopd). */
#define ESTOP_DEFAULT_TAG_CHECKS 10u
#define ESTOP_DEFAULT_TAG_WINDOW_US 100000u
#define ESTOP_TAG_CHECKS_ALL 0u

/* Accepted configuration ranges (checked by estop_init). */
#define ESTOP_TIMEOUT_MIN_US 1000u
#define ESTOP_TIMEOUT_MAX_US 60000000u
#define ESTOP_BRAKE_PERIOD_MIN_US 1000u
#define ESTOP_BRAKE_PERIOD_MAX_US 25000u /* well inside the brake controller's 50 ms */
#define ESTOP_STATUS_PERIOD_MIN_US 10000u
#define ESTOP_STATUS_PERIOD_MAX_US 1000000u
#define ESTOP_CAN_ID_MAX 0x7FFu
#define ESTOP_SLOW_LEVEL_MIN 1u
#define ESTOP_SLOW_LEVEL_MAX 99u
#define ESTOP_TAG_CHECKS_MAX 100u
#define ESTOP_TAG_WINDOW_MIN_US 1000u
#define ESTOP_TAG_WINDOW_MAX_US 1000000u

typedef enum {
    ESTOP_OK = 0,
    ESTOP_ERR_NULL_ARG = -1,
    ESTOP_ERR_TIMEOUT = -2,        /* timeout_us outside its range */
    ESTOP_ERR_WARN = -3,           /* warn_us not in 1 .. slow_us */
    ESTOP_ERR_STOP_ID = -4,        /* stop_id is 0, 1, 2, 3 or ESTOP_MAGIC_REQUEST */
    ESTOP_ERR_CAN_ID = -5,         /* CAN id over 11 bits, or both ids equal */
    ESTOP_ERR_DATA_ID = -6,        /* both data ids equal */
    ESTOP_ERR_RELEASE_COUNT = -7,  /* release_packets is 0 */
    ESTOP_ERR_BRAKE_PERIOD = -8,   /* brake_period_us outside its range */
    ESTOP_ERR_STATUS_PERIOD = -9,  /* status_period_us outside its range or below the brake period */
    ESTOP_ERR_NOT_INIT = -10,      /* the core was never initialised, or its init failed */
    ESTOP_ERR_SLOT = -11,          /* slot index out of range */
    ESTOP_ERR_SLOT_CLOSED = -12,   /* bytes for a slot that is not open */
    ESTOP_ERR_KEY = -13,           /* key_len is neither 0 (no key) nor ESTOP_KEY_LEN */
    ESTOP_ERR_SESSION = -14,       /* session is 0 */
    ESTOP_ERR_SLOW = -15,          /* slow_us not in 1 .. timeout_us */
    ESTOP_ERR_SLOW_LEVEL = -16,    /* slow_level not in 1 .. 99 */
    ESTOP_ERR_TAG_BUDGET = -17     /* tag_checks over 100, or tag_window_us outside its range */
} estop_err_t;

typedef struct {
    uint32_t timeout_us;       /* T: UDP silence that stops the unit (latched) */
    uint32_t slow_us;          /* S: UDP silence that starts a controlled stop (SLOWING, not
                                  latched); S = T: never */
    uint32_t warn_us;          /* W: silence that raises the link-degraded flag;
                                  0 < W <= S <= T */
    uint32_t stop_id;          /* the vehicle's TCP stop message id */
    uint32_t brake_can_id;     /* ESTOP_BRAKE */
    uint32_t status_can_id;    /* ESTOP_STATUS */
    uint16_t brake_data_id;    /* enters the ESTOP_BRAKE CRC, never sent */
    uint16_t status_data_id;   /* enters the ESTOP_STATUS CRC, never sent */
    uint32_t release_packets;  /* valid packets needed since the stop before a RELEASE */
    uint32_t brake_period_us;
    uint32_t status_period_us;
    uint32_t tag_window_us;    /* the window of the tag-check budget (see tag_checks) */
    uint64_t session;          /* N: drawn by the host from a cryptographic source at every
                                  boot; never 0 (a unit without a key has one too) */
    uint8_t slow_level;        /* L: brake_level while SLOWING, percent 1..99 */
    uint8_t tag_checks;        /* tag checks of control packets per tag_window_us, for each
                                  remote id with a place (its next counters) and for all
                                  others together; the rest are dropped unchecked (a bounded
                                  cost per window, PROTOCOL.md 5). ESTOP_TAG_CHECKS_ALL (0):
                                  every tag is checked */
    uint8_t key_len;           /* 0: no key; ESTOP_KEY_LEN: key holds the key */
    uint8_t key[ESTOP_KEY_LEN];
} estop_config_t;

typedef struct {
    uint32_t id;
    uint8_t dlc;
    uint8_t data[ESTOP_CAN_DLC];
} estop_can_frame_t;

/* Every counter saturates at UINT32_MAX: it never wraps back to a small number. */
typedef struct {
    uint32_t udp_valid;
    uint32_t udp_invalid;
    uint32_t udp_stops;       /* stop and lift datagrams (PROTOCOL.md 1), whatever their tag */
    uint32_t tcp_frames;      /* frames with a good crc */
    uint32_t tcp_bad_crc;     /* frames with a bad crc (connection closed) */
    uint32_t tcp_unknown_id;  /* good crc, unknown msg_id (NAK 1) */
    uint32_t releases_accepted;
    uint32_t releases_refused;
    uint32_t stops[ESTOP_REASON_COUNT]; /* transitions into STOPPED, by reason; [1] counts boot */
    uint32_t slowdowns;       /* transitions ARMED -> SLOWING */
    uint32_t rearms;          /* transitions SLOWING -> ARMED (the link came back) */
    uint32_t faults;          /* faults reported by the host, in any state */
    /* Messages that needed authentication (control packets and RELEASE on a unit with a key)
     * and failed it, by the first check that failed (PROTOCOL.md 5). */
    uint32_t auth_bad_tag;     /* wrong tag, or none: a plain control packet or RELEASE, a
                                  60-byte packet without the ESU2 magic */
    uint32_t auth_bad_session;
    uint32_t auth_old_counter; /* replayed or stale: not above the highest kept */
    uint32_t auth_table_full;  /* a 9th remote id */
    /* Control packets dropped unchecked: the tag-check budget of their remote id (or of the
     * ids without a place) was spent in this window. Counted as invalid, not as failures.
     * One that names a remote id with a place raises that remote's UDP counter to its own
     * (PROTOCOL.md 5): it can never be authenticated later. */
    uint32_t auth_unchecked;
} estop_counters_t;

/* Filled by every entry point: the counts and flags always; can[0 .. n_can-1] and, with
 * has_reply, reply[0 .. reply_len-1]. Bytes beyond those are left as they were. */
typedef struct {
    estop_can_frame_t can[ESTOP_OUT_MAX_CAN];
    uint8_t n_can;
    uint8_t has_reply;                   /* reply holds a frame of reply_len bytes for the
                                            input's slot */
    uint8_t reply_len;                   /* 16 (plain) or 48 (reply frame) */
    uint8_t reply[ESTOP_REPLY_MAX];
    uint8_t close_slot;                  /* the host must close the input's slot (bad crc) */
    uint8_t state_changed;               /* the state changed during this call */
    uint8_t changed_by_clock;            /* ... and the change came from the clock (slow time,
                                            timeout or a tick that went backwards), not from
                                            the input */
    uint8_t clock_state;                 /* state and reason after the clock's part of the
                                            call, before the input. When they differ from
                                            state and reason below, the clock changed the
                                            state first and the input changed it again: two
                                            changes, each with its cause */
    uint8_t clock_reason;
    uint8_t state;                       /* state and reason after the call */
    uint8_t reason;
    uint8_t flags;
    uint32_t next_call_us;               /* call again (estop_tick) when the tick reaches this */
} estop_out_t;

typedef struct {
    uint8_t open;
    uint8_t fill;
    uint8_t buf[ESTOP_REQ_FRAME_LEN];
} estop_slot_t;

/* A remote id and the counters kept for it this session (PROTOCOL.md 5). */
typedef struct {
    uint64_t counter[2];       /* [0] UDP: the highest control packet counter authenticated or
                                  dropped unchecked under this id; [1] TCP: the highest
                                  counter authenticated on either channel (a RELEASE must be
                                  above it); each meaningful where seen has its bit */
    uint32_t id;
    uint8_t used;
    uint8_t seen;              /* bit 0: counter[0] is kept; bit 1: counter[1] */
    uint8_t checks;            /* tag checks of its control packets in the current window */
} estop_remote_t;

/* Caller-owned state. Treat as opaque: read it only through the functions below. */
typedef struct {
    uint32_t magic;            /* set by a successful estop_init */
    estop_config_t cfg;
    uint32_t now_us;           /* tick of the latest call */
    uint8_t state;
    uint8_t reason;
    uint8_t link_fresh;        /* a valid packet arrived and has not yet aged past the timeout */
    uint8_t last_neutral;      /* the latest valid packet had gas_brake <= 0 */
    uint32_t last_valid_us;    /* tick of the latest valid packet (meaningful while link_fresh) */
    uint32_t valid_run;        /* valid packets since boot, the latest stop or the latest silence
                                  of the timeout, whichever is latest (saturating) */
    uint8_t slow_run;          /* valid packets since SLOWING began (up to ESTOP_REARM_PACKETS) */
    uint32_t brake_due_us;
    uint32_t status_due_us;
    uint8_t brake_counter;
    uint8_t status_counter;
    uint8_t status_valid;      /* valid packets since the last status frame, saturating */
    uint8_t status_invalid;    /* invalid packets since the last status frame, saturating */
    uint8_t status_auth_failed; /* authentication failures since the last status frame, sat. */
    uint8_t status_stops;      /* stops (boot not counted) since the last status frame, sat. */
    uint8_t status_slowdowns;  /* slow-downs since the last status frame, saturating */
    uint8_t gap_known;         /* a valid packet arrived before, and the gap since is measurable */
    uint32_t silences;         /* gaps between valid packets of at least the warn time */
    uint32_t gaps[ESTOP_GAP_BINS]; /* saturating counts of gaps between valid packets */
    estop_counters_t counters;
    estop_slot_t slots[ESTOP_MAX_SLOTS];
    estop_b2s_key_t mac;       /* the state after the key block (the key itself is not kept) */
    uint32_t tag_window_us;    /* tick at which the current tag-check window began */
    uint8_t tag_window_open;   /* it has not yet lasted cfg.tag_window_us (looked at in every
                                  call, so that no gap, 2^32 us included, brings it back) */
    uint8_t newcomer_checks;   /* tag checks this window from the shared allowance (new ids,
                                  counters far ahead) */
    estop_remote_t remotes[ESTOP_MAX_REMOTES];
} estop_core_t;

/* A read-out of everything observable. */
typedef struct {
    uint8_t state;
    uint8_t reason;
    uint8_t flags;
    uint8_t link_live;          /* a RELEASE would pass the link check now */
    uint32_t valid_run;
    uint32_t link_age_us;       /* saturates at UINT32_MAX when no fresh packet */
    estop_counters_t counters;
} estop_status_t;

/* The link's record: what `estop link` turns into false stops per hour. */
typedef struct {
    uint32_t valid;                  /* valid control packets (= counters.udp_valid) */
    uint32_t silences;               /* gaps of at least the warn time between them */
    uint32_t slowdowns;              /* silences that reached the slow time (= counters.slowdowns) */
    uint32_t timeouts;               /* silences that reached the timeout while ARMED or
                                        SLOWING (= counters.stops[udp timeout]) */
    uint32_t gaps[ESTOP_GAP_BINS];   /* the gap histogram (saturating counts) */
} estop_link_stats_t;

/* Fills cfg with the defaults of PROTOCOL.md (slow time = timeout, warn time = half of it,
 * slow level 30 %, no key). The session is left 0: the host must draw one (estop_init
 * refuses 0). */
void estop_config_default(estop_config_t *cfg);
/* Checks a configuration; returns ESTOP_OK or the first error found. */
estop_err_t estop_config_check(const estop_config_t *cfg);
/* Boots the unit STOPPED (reason boot) at now_us. On error the core stays unusable. */
estop_err_t estop_init(estop_core_t *core, const estop_config_t *cfg, uint32_t now_us);

/* Advances time: slow-down, timeout stop, link-degraded flag, periodic frames. */
estop_err_t estop_tick(estop_core_t *core, uint32_t now_us, estop_out_t *out);
/* One UDP datagram of any length (data may be NULL when len is 0): a control packet, or a stop
 * or lift datagram (a request frame whose msg_id is the stop ID or LIFT: it stops the unit,
 * with the reason of its msg_id, whatever its tag). */
estop_err_t estop_udp_rx(estop_core_t *core, const uint8_t *data, size_t len, uint32_t now_us,
                         estop_out_t *out);
/* A TCP connection was accepted into slot (0 .. ESTOP_MAX_SLOTS-1). */
estop_err_t estop_tcp_open(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out);
/* The host closed slot (peer gone, or on the core's request). */
estop_err_t estop_tcp_close(estop_core_t *core, uint32_t slot, uint32_t now_us, estop_out_t *out);
/* TCP bytes for slot. Consumes up to one complete frame; *consumed says how many bytes. */
estop_err_t estop_tcp_rx(estop_core_t *core, uint32_t slot, const uint8_t *data, size_t len,
                         size_t *consumed, uint32_t now_us, estop_out_t *out);
/* The host reports a fault it cannot mend (e.g. CAN frames keep failing to send). */
estop_err_t estop_fault(estop_core_t *core, uint32_t now_us, estop_out_t *out);

/* Read-out at the tick of the latest call. */
estop_err_t estop_get_status(const estop_core_t *core, estop_status_t *status);
/* The link's record, for the host to log. */
estop_err_t estop_get_link_stats(const estop_core_t *core, estop_link_stats_t *stats);
/* The bin of a gap of gap_us microseconds (a pure function, for hosts and tests). */
uint32_t estop_gap_bin(uint32_t gap_us);
/* A short constant name for an error code, for host logs. */
const char *estop_err_name(estop_err_t err);
/* Constant names for states and reasons ("?" when out of range). */
const char *estop_state_name(uint32_t state);
const char *estop_reason_name(uint32_t reason);

#ifdef __cplusplus
}
#endif

#endif /* ESTOP_CORE_H */
