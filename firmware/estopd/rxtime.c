#include "rxtime.h"

#define NS_PER_US 1000
#define NS_PER_S 1000000000
#define US_PER_S 1000000u

uint64_t rxtime_to_mono_us(const struct timespec *stamp, const struct timespec *real_now,
                           uint64_t mono_now_us)
{
    int64_t dsec;
    int64_t age_ns;
    uint64_t age_us;

    /* Negative seconds are no stamp the kernel makes; and with both >= 0 the difference fits. */
    if (stamp->tv_sec < 0 || real_now->tv_sec < 0) {
        return mono_now_us;
    }
    dsec = (int64_t)real_now->tv_sec - (int64_t)stamp->tv_sec;
    if (dsec < 0) {
        return mono_now_us; /* stamped "after" the reading: the wall clock went back since */
    }
    if ((uint64_t)dsec > mono_now_us / US_PER_S + 1u) {
        return 0u; /* older than the monotonic clock; also keeps the nanoseconds below in range */
    }
    age_ns = dsec * NS_PER_S + ((int64_t)real_now->tv_nsec - (int64_t)stamp->tv_nsec);
    if (age_ns <= 0) {
        return mono_now_us;
    }
    age_us = (uint64_t)(age_ns / NS_PER_US);
    return age_us >= mono_now_us ? 0u : mono_now_us - age_us;
}

uint64_t rxtime_feed_us(uint64_t recv_us, uint64_t last_call_us)
{
    return recv_us > last_call_us ? recv_us : last_call_us;
}
