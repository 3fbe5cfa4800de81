/*
 * estop_config: what a host uses without a core: the configuration's defaults and its check
 * (estop_init checks it again), and the names of the codes the core returns and reports.
 */
#include "estop_core.h"

void estop_config_default(estop_config_t *cfg)
{
    if (cfg != NULL) {
        uint32_t i;
        cfg->timeout_us = ESTOP_DEFAULT_TIMEOUT_US;
        cfg->slow_us = ESTOP_DEFAULT_TIMEOUT_US; /* S = T: never SLOWING (version 2) */
        cfg->warn_us = ESTOP_DEFAULT_TIMEOUT_US / 2u;
        cfg->slow_level = (uint8_t)ESTOP_DEFAULT_SLOW_LEVEL;
        cfg->stop_id = ESTOP_DEFAULT_STOP_ID;
        cfg->brake_can_id = ESTOP_DEFAULT_BRAKE_CAN_ID;
        cfg->status_can_id = ESTOP_DEFAULT_STATUS_CAN_ID;
        cfg->brake_data_id = (uint16_t)ESTOP_DEFAULT_BRAKE_DATA_ID;
        cfg->status_data_id = (uint16_t)ESTOP_DEFAULT_STATUS_DATA_ID;
        cfg->release_packets = ESTOP_DEFAULT_RELEASE_PACKETS;
        cfg->brake_period_us = ESTOP_DEFAULT_BRAKE_PERIOD_US;
        cfg->status_period_us = ESTOP_DEFAULT_STATUS_PERIOD_US;
        cfg->tag_checks = (uint8_t)ESTOP_DEFAULT_TAG_CHECKS;
        cfg->tag_window_us = ESTOP_DEFAULT_TAG_WINDOW_US;
        cfg->session = 0u; /* the host's to draw (estop_init refuses 0) */
        cfg->key_len = 0u;
        /*@ loop invariant 0 <= i <= 32;
            loop assigns i, cfg->key[0 .. 31];
            loop variant 32 - i; */
        for (i = 0u; i < ESTOP_KEY_LEN; i++) {
            cfg->key[i] = 0u;
        }
    }
}

estop_err_t estop_config_check(const estop_config_t *cfg)
{
    estop_err_t err = ESTOP_OK;
    if (cfg == NULL) {
        err = ESTOP_ERR_NULL_ARG;
    } else if ((cfg->timeout_us < ESTOP_TIMEOUT_MIN_US) ||
               (cfg->timeout_us > ESTOP_TIMEOUT_MAX_US)) {
        err = ESTOP_ERR_TIMEOUT;
    } else if ((cfg->slow_us == 0u) || (cfg->slow_us > cfg->timeout_us)) {
        err = ESTOP_ERR_SLOW;
    } else if ((cfg->warn_us == 0u) || (cfg->warn_us > cfg->slow_us)) {
        err = ESTOP_ERR_WARN;
    } else if ((cfg->slow_level < ESTOP_SLOW_LEVEL_MIN) ||
               (cfg->slow_level > ESTOP_SLOW_LEVEL_MAX)) {
        err = ESTOP_ERR_SLOW_LEVEL;
    } else if ((cfg->stop_id == 0u) || (cfg->stop_id == ESTOP_MSG_STATUS) ||
               (cfg->stop_id == ESTOP_MSG_RELEASE) || (cfg->stop_id == ESTOP_MSG_LIFT) ||
               (cfg->stop_id == ESTOP_MAGIC_REQUEST)) {
        err = ESTOP_ERR_STOP_ID;
    } else if ((cfg->brake_can_id > ESTOP_CAN_ID_MAX) || (cfg->status_can_id > ESTOP_CAN_ID_MAX) ||
               (cfg->brake_can_id == cfg->status_can_id)) {
        err = ESTOP_ERR_CAN_ID;
    } else if (cfg->brake_data_id == cfg->status_data_id) {
        err = ESTOP_ERR_DATA_ID;
    } else if (cfg->release_packets == 0u) {
        err = ESTOP_ERR_RELEASE_COUNT;
    } else if ((cfg->brake_period_us < ESTOP_BRAKE_PERIOD_MIN_US) ||
               (cfg->brake_period_us > ESTOP_BRAKE_PERIOD_MAX_US)) {
        err = ESTOP_ERR_BRAKE_PERIOD;
    } else if ((cfg->status_period_us < ESTOP_STATUS_PERIOD_MIN_US) ||
               (cfg->status_period_us > ESTOP_STATUS_PERIOD_MAX_US) ||
               (cfg->status_period_us < cfg->brake_period_us)) {
        err = ESTOP_ERR_STATUS_PERIOD;
    } else if ((cfg->tag_checks > ESTOP_TAG_CHECKS_MAX) ||
               (cfg->tag_window_us < ESTOP_TAG_WINDOW_MIN_US) ||
               (cfg->tag_window_us > ESTOP_TAG_WINDOW_MAX_US)) {
        err = ESTOP_ERR_TAG_BUDGET;
    } else if ((cfg->key_len != 0u) && (cfg->key_len != ESTOP_KEY_LEN)) {
        err = ESTOP_ERR_KEY;
    } else if (cfg->session == 0u) {
        err = ESTOP_ERR_SESSION;
    } else {
        err = ESTOP_OK;
    }
    return err;
}

const char *estop_err_name(estop_err_t err)
{
    static const char *const names[] = {
        "ok",           "null_arg",         "bad_timeout",  "bad_warn_time",
        "bad_stop_id",  "bad_can_id",       "bad_data_id",  "bad_release_count",
        "bad_brake_period", "bad_status_period", "not_initialised", "bad_slot",
        "slot_closed",  "bad_key",          "bad_session",  "bad_slow_time",
        "bad_slow_level", "bad_tag_budget"};
    const char *name = "unknown_error";
    const size_t n = sizeof(names) / sizeof(names[0]);
    const int count = (int)n;
    /* Range first: negating an arbitrary int (INT_MIN) would overflow. */
    if (((int)err <= 0) && ((int)err > -count)) {
        name = names[-(int)err];
    }
    return name;
}

const char *estop_state_name(uint32_t state)
{
    static const char *const names[] = {"STOPPED", "ARMED", "SLOWING"};
    return (state < ESTOP_STATE_COUNT) ? names[state] : "?";
}

const char *estop_reason_name(uint32_t reason)
{
    static const char *const names[] = {"none",  "boot", "tcp_stop", "udp_timeout",
                                        "fault", "lift"};
    return (reason < ESTOP_REASON_COUNT) ? names[reason] : "?";
}
