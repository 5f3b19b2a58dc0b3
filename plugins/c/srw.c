/*
 * SRW, slack-aware shortest remaining work: robots already out of actions first, ordered by
 * remaining work (the client's hint, else a Gittins index learned from finished tasks) aged by
 * the wait ratio; the rest by deadline.
 *
 * Twin of the server's native `srw` policy (server/src/scheduler/srw.rs, "Exact semantics");
 * the same order bit for bit, checked by server/tests/plugin_twins.rs. With `now` in µs:
 *   1. Deadline d = exec_ends_at_us, or arrived_at_us when absent (present bit 1 clear). Due
 *      iff slack = 0 or d <= now.
 *   2. Work urgency u: with hints = 1 and a hint, 1 / max(1, rounds) (present bit 3), or with
 *      only seconds (bit 4) and a known |E_last| (bit 0), 1 / max(1, seconds / |E_last|)
 *      (seconds: the f32 widened; |E_last|: kairos_secs(ns), i.e. Duration::as_secs_f64;
 *      usable only when seconds is finite and >= 0 and |E_last| > 0); otherwise, once `warmup`
 *      tasks have finished, the Gittins index G(rounds_completed); otherwise 0.
 *   3. Due requests with due_order = 0 (work): score = u / max(1 - w, 0.01), w the wait ratio
 *      (kairos_wait_ratio: Eq. 1 in whole µs), clamped to 0 unless finite and > 0; ordered by
 *      the score's bit pattern descending: minor = UINT64_MAX - bits. With due_order = 1
 *      (deadline), and for requests not due: d ascending, minor = d.
 *   4. Due requests first (major = 0 if due, else 1); ties by arrived_at_us, then request,
 *      ascending: the server's own tie-break.
 * The Gittins index is rebuilt lazily, only when it is read and only when the number of
 * observed tasks exceeds built_at + built_at / 16: the same moments as the native policy, so
 * the same counts go into the same index. The state lives in this instance; it is lost (as
 * the native policy's would be on a restart) if the server discards the instance.
 * Parameters (defaults): hints (1; 0 or 1), warmup (20; whole 0..1e6), slack (1; 0 or 1),
 * due_order (0 = work, 1 = deadline; 0).
 */
#include <stdlib.h>

#include "priority_policy.h"
#include "kairos_policy.h"

#define MIN_UNWAITED 0.01

/* ---- The Gittins index over task round counts (native: GittinsIndex). ---- */

static uint64_t *counts;  /* counts[n]: finished tasks that took n rounds */
static size_t counts_len; /* the native Vec's len: longest task seen + 1, or 0 */
static uint64_t observed;
static double *gittins;   /* gittins_len == counts_len after a rebuild */
static size_t gittins_len;
static uint64_t built_at;

static void gittins_observe(uint32_t rounds) {
    if (rounds == 0) return;
    size_t n = rounds;
    /* wasm32: (n + 1) * 8 bytes must not wrap (the native policy cannot hold that many either). */
    if (n >= SIZE_MAX / sizeof(uint64_t) - 1) abort();
    if (counts_len <= n) {
        uint64_t *grown = realloc(counts, (n + 1) * sizeof(uint64_t));
        if (!grown) abort();
        memset(grown + counts_len, 0, (n + 1 - counts_len) * sizeof(uint64_t));
        counts = grown;
        counts_len = n + 1;
    }
    counts[n] += 1;
    observed += 1;
}

static void gittins_rebuild(void) {
    size_t len = counts_len;
    /* survivors[a] = tasks with more than a rounds. */
    uint64_t *survivors = calloc(len + 1, sizeof(uint64_t));
    double *index = len ? realloc(gittins, len * sizeof(double)) : gittins;
    if (!survivors || (len && !index)) abort();
    gittins = index;
    for (size_t a = len; a-- > 0;) {
        survivors[a] = survivors[a + 1] + (a + 1 < len ? counts[a + 1] : 0);
    }
    double last = 0.0;
    for (size_t a = 0; a < len; a++) {
        uint64_t alive = survivors[a];
        if (alive == 0) {
            gittins[a] = last;
            continue;
        }
        double best = 0.0;
        uint64_t invested = 0;
        for (size_t delta = 1; delta <= len - a; delta++) {
            invested += survivors[a + delta - 1];
            uint64_t finished = alive - survivors[a + delta];
            double ratio = (double)finished / (double)invested;
            if (ratio > best) best = ratio;
        }
        last = best;
        gittins[a] = best;
    }
    gittins_len = len;
    built_at = observed;
    free(survivors);
}

static double gittins_get(uint32_t age) {
    if (observed > built_at + built_at / 16) gittins_rebuild();
    if (gittins_len == 0) return 0.0;
    size_t at = age < gittins_len - 1 ? age : gittins_len - 1;
    return gittins[at];
}

/* ---- Ordering. ---- */

typedef struct {
    bool hints;
    uint32_t warmup;
    bool slack;
    bool by_deadline;
} config_t;

/* The client's hint as a round count (>= 1), or 0 when unusable. `present` says which of the
 * other arguments are known. */
static double hinted_rounds(uint8_t present, uint32_t rounds, float seconds, uint64_t last_exec_ns) {
    if (present & KAIROS_PRESENT_REMAINING_ROUNDS) {
        double r = (double)rounds;
        return r > 1.0 ? r : 1.0;
    }
    const uint8_t needed = KAIROS_PRESENT_REMAINING_SECONDS | KAIROS_PRESENT_LAST_EXEC;
    if ((present & needed) != needed) return 0.0;
    double secs = (double)seconds;
    double exec = kairos_secs(last_exec_ns);
    if (!(isfinite(secs) && secs >= 0.0 && exec > 0.0)) return 0.0;
    double r = secs / exec;
    return r > 1.0 ? r : 1.0;
}

/* The work urgency of row `i`. */
static double urgency(const config_t *c, const exports_kairos_policy_priority_pending_columns_t *v,
                      size_t i) {
    if (c->hints) {
        double rounds = hinted_rounds(v->present.ptr[i], v->remaining_rounds.ptr[i],
                                      v->remaining_seconds.ptr[i], v->last_exec_ns.ptr[i]);
        if (rounds > 0.0) return 1.0 / rounds;
    }
    if (observed >= c->warmup) return gittins_get(v->rounds_completed.ptr[i]);
    return 0.0;
}

static bool is_flag(double v) { return v == 0.0 || v == 1.0; }

/* Fills `c` from `params`, or returns why not. */
static const char *parse_params(const exports_kairos_policy_priority_list_param_t *params,
                                config_t *c) {
    static const char *const known[] = {"due_order", "hints", "slack", "warmup", NULL};
    *c = (config_t){true, 20, true, false};
    if (kairos_param_unknown(params->ptr, params->len, known)) {
        return "srw: unknown parameter (expected due_order, hints, slack, warmup)";
    }
    const kairos_policy_types_param_t *p;
    if ((p = kairos_param_find(params->ptr, params->len, "hints"))) {
        if (!is_flag(p->value)) return "srw: hints must be 0 or 1";
        c->hints = p->value == 1.0;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "warmup"))) {
        double v = p->value;
        if (!(isfinite(v) && v >= 0.0 && v == trunc(v) && v <= 1e6)) {
            return "srw: warmup must be a whole number between 0 and 10^6";
        }
        c->warmup = (uint32_t)v;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "slack"))) {
        if (!is_flag(p->value)) return "srw: slack must be 0 or 1";
        c->slack = p->value == 1.0;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "due_order"))) {
        if (!is_flag(p->value)) return "srw: due_order must be 0 (work) or 1 (deadline)";
        c->by_deadline = p->value == 1.0;
    }
    return NULL;
}

bool exports_kairos_policy_priority_rank(uint64_t now_us,
                                         exports_kairos_policy_priority_pending_columns_t *pending,
                                         exports_kairos_policy_priority_list_param_t *params,
                                         exports_kairos_policy_priority_ranking_t *ret,
                                         priority_policy_string_t *err) {
    config_t c;
    const char *problem = parse_params(params, &c);
    if (problem) {
        priority_policy_string_dup(err, problem);
    } else {
        size_t n = pending->request.len;
        const uint64_t *arrived_us = pending->arrived_at_us.ptr;
        const uint64_t *ends_us = pending->exec_ends_at_us.ptr;
        const uint64_t *started_us = pending->task_started_at_us.ptr;
        const uint64_t *wait_ns = pending->wait_ns.ptr;
        const uint8_t *present = pending->present.ptr;
        uint64_t *major = kairos_u64s(n), *minor = kairos_u64s(n);
        /* In row order, like the native key function: the Gittins index is rebuilt on the
         * first read that needs it, which must be the same read in both twins. */
        for (size_t i = 0; i < n; i++) {
            uint64_t deadline = present[i] & KAIROS_PRESENT_EXEC_ENDS ? ends_us[i] : arrived_us[i];
            bool due = !c.slack || deadline <= now_us;
            major[i] = !due;
            if (due && !c.by_deadline) {
                double unwaited = 1.0 - kairos_wait_ratio(now_us, started_us[i], wait_ns[i]);
                if (!(unwaited > MIN_UNWAITED)) unwaited = MIN_UNWAITED;
                double score = urgency(&c, pending, i) / unwaited;
                if (!(isfinite(score) && score > 0.0)) score = 0.0;
                minor[i] = kairos_desc(kairos_f64_bits(score));
            } else {
                minor[i] = deadline;
            }
        }
        *ret = (exports_kairos_policy_priority_ranking_t){
            .tag = EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_KEYS,
            .val.keys = {{major, n}, {minor, n}},
        };
    }
    exports_kairos_policy_priority_pending_columns_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return problem == NULL;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    gittins_observe(summary->rounds);
}
