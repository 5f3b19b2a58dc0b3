/*
 * Helpers for Kairos policy plugins written in C.
 *
 * Include the world's generated header first (`horizon_policy.h` or `priority_policy.h`, from
 * since_vX.Y.Z/ for the WIT version the plugin targets), then this file. Everything here is
 * header-only and works with the bindings of every version; only kairos_u64s allocates.
 *
 * The helpers reproduce the server's own conventions exactly, so a C plugin can give the
 * same answers as a native Rust policy bit for bit:
 *   - kairos_secs(ns) is Rust's Duration::as_secs_f64 (whole seconds and the remainder are
 *     converted separately);
 *   - kairos_wait_ratio(...) is PendingView::wait_ratio (paper Eq. 1);
 *   - parameter rules match the server's parsing: names are compared byte for byte, a
 *     "count" is a finite whole number in [1, 1e9], a "real" is finite and >= a minimum.
 * Build with -ffp-contract=off: the server never fuses a multiply and an add, and neither
 * may a twin.
 */
#ifndef KAIROS_POLICY_H
#define KAIROS_POLICY_H

#include <math.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if !defined(__BINDINGS_HORIZON_POLICY_H) && !defined(__BINDINGS_PRIORITY_POLICY_H)
#error "include horizon_policy.h or priority_policy.h before kairos_policy.h"
#endif

/* Bits of `pending-columns.present` (priority@0.2.0): which optional fields a row has. A field
 * whose bit is clear holds 0 in its column, which must not be read as a real 0 (a task with no
 * reported execution is not one whose execution took 0 ns). */
#define KAIROS_PRESENT_LAST_EXEC 1u          /* last-exec-ns */
#define KAIROS_PRESENT_EXEC_ENDS 2u          /* exec-ends-at-us */
#define KAIROS_PRESENT_LAST_GEN 4u           /* last-gen-ns */
#define KAIROS_PRESENT_REMAINING_ROUNDS 8u   /* remaining-rounds */
#define KAIROS_PRESENT_REMAINING_SECONDS 16u /* remaining-seconds */

/* The bit pattern of `v`, like Rust's f64::to_bits. For v >= 0 (and not NaN) the patterns
 * order like the numbers, so a non-negative score can be used as an integer sort key. */
static inline uint64_t kairos_f64_bits(double v) {
    uint64_t bits;
    memcpy(&bits, &v, sizeof bits);
    return bits;
}

/* The ascending key that orders like `k` descending (Rust's Reverse(k) for a u64): the server
 * sorts keys ascending only, so a policy that wants "larger first" answers UINT64_MAX - k. */
static inline uint64_t kairos_desc(uint64_t k) {
    return UINT64_MAX - k;
}

/* A key column of `n` rows: malloc'd, because the bindings' post-return hands every returned
 * list to free(); NULL for n = 0 (an empty list). Aborts when out of memory: a trap makes the
 * server fall back to its built-in policy, where a short list would be a wrong answer. */
static inline uint64_t *kairos_u64s(size_t n) {
    if (n == 0) return NULL;
    uint64_t *p = n <= SIZE_MAX / sizeof(uint64_t) ? malloc(n * sizeof(uint64_t)) : NULL;
    if (!p) abort();
    return p;
}

/* Seconds in `ns` nanoseconds, computed like Rust's Duration::as_secs_f64. */
static inline double kairos_secs(uint64_t ns) {
    return (double)(ns / 1000000000u) + (double)(uint32_t)(ns % 1000000000u) / 1e9;
}

/* The wait ratio of paper Eq. 1, like the server's PendingView::wait_ratio: wait and life
 * (now - task start, 0 if negative) in whole microseconds (ns / 1000 truncating), converted
 * to double and divided once, clamped to [0, 1]; 0 for a task that starts at `now`. */
static inline double kairos_wait_ratio(uint64_t now_us, uint64_t task_started_at_us, uint64_t wait_ns) {
    uint64_t life_us = now_us > task_started_at_us ? now_us - task_started_at_us : 0;
    if (life_us == 0) return 0.0;
    double w = (double)(wait_ns / 1000) / (double)life_us;
    return w < 0.0 ? 0.0 : w > 1.0 ? 1.0 : w;
}

/* Whether parameter `p` is named `name`. */
static inline bool kairos_param_is(const kairos_policy_types_param_t *p, const char *name) {
    size_t n = strlen(name);
    return p->name.len == n && memcmp(p->name.ptr, name, n) == 0;
}

/* The parameter named `name`, or NULL. */
static inline const kairos_policy_types_param_t *
kairos_param_find(const kairos_policy_types_param_t *params, size_t len, const char *name) {
    for (size_t i = 0; i < len; i++) {
        if (kairos_param_is(&params[i], name)) return &params[i];
    }
    return NULL;
}

/* The first parameter whose name is not in the NULL-terminated list `known`, or NULL.
 * Parameters arrive sorted by name, so "first" is the same one the server would name. */
static inline const kairos_policy_types_param_t *
kairos_param_unknown(const kairos_policy_types_param_t *params, size_t len, const char *const *known) {
    for (size_t i = 0; i < len; i++) {
        bool ok = false;
        for (const char *const *k = known; *k; k++) {
            if (kairos_param_is(&params[i], *k)) { ok = true; break; }
        }
        if (!ok) return &params[i];
    }
    return NULL;
}

/* A finite real >= min. */
static inline bool kairos_is_real(double v, double min) {
    return isfinite(v) && v >= min;
}

/* A whole number of actions: finite, >= 1, no fraction, <= 1e9. */
static inline bool kairos_is_count(double v) {
    return isfinite(v) && v >= 1.0 && v == trunc(v) && v <= 1e9;
}

/* Copies the bytes of a parameter's name into a NUL-terminated buffer (truncating). */
static inline void kairos_param_name(const kairos_policy_types_param_t *p, char *buf, size_t cap) {
    size_t n = p->name.len < cap - 1 ? p->name.len : cap - 1;
    memcpy(buf, p->name.ptr, n);
    buf[n] = '\0';
}

#endif /* KAIROS_POLICY_H */
