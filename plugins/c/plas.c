/*
 * Autellix PLAS (program-level attained service) priority policy.
 *
 * Twin of the server's native `plas` policy (server/src/scheduler/plas.rs); the same order,
 * checked by server/tests/plugin_twins.rs. All times in whole microseconds (ns / 1000,
 * truncating, as Rust's Duration::as_micros):
 *   1. Thresholds T_0 = q, T_i = T_{i-1} + q*g^i (saturating u64), i = 0 .. K-2. The queue of
 *      a service s is the number of thresholds <= s.
 *   2. Starving iff (double)queued >= beta * (double)max(q, s); a starving request goes to
 *      queue 0.
 *   3. Order by (queue, arrived-at-us, request) ascending: the answer is major = queue and an
 *      empty minor (all 0); the server breaks ties by (arrived-at-us, request) itself.
 * Parameters (defaults): queues K (8, whole 1..64), quantum_ms q (1000, > 0, rounded to whole
 * microseconds in [1, 1e15]), growth g (2, whole 1..1000), beta (8, finite > 0).
 */
#include "priority_policy.h"
#include "kairos_policy.h"

#define MAX_QUEUES 64

static uint64_t sat_add(uint64_t a, uint64_t b) { return a + b < a ? UINT64_MAX : a + b; }
static uint64_t sat_mul(uint64_t a, uint64_t b) {
    return (b != 0 && a > UINT64_MAX / b) ? UINT64_MAX : a * b;
}

/* Reads the parameters; on error writes the reason into `err` and returns false. */
static bool read_params(const exports_kairos_policy_priority_list_param_t *params, uint32_t *queues,
                        uint64_t *quantum_us, uint32_t *growth, double *beta, priority_policy_string_t *err) {
    static const char *const known[] = {"beta", "growth", "quantum_ms", "queues", NULL};
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (p) {
        priority_policy_string_dup(err, "plas: unknown parameter (expected beta, growth, quantum_ms, queues)");
        return false;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "queues"))) {
        if (!kairos_is_count(p->value) || p->value > MAX_QUEUES) {
            priority_policy_string_dup(err, "plas: queues must be a whole number between 1 and 64");
            return false;
        }
        *queues = (uint32_t)p->value;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "quantum_ms"))) {
        double us = round(p->value * 1e3);
        if (!kairos_is_real(p->value, 0.0) || p->value <= 0.0 || !(us >= 1.0 && us <= 1e15)) {
            priority_policy_string_dup(err, "plas: quantum_ms must be between 0.001 and 10^12 ms");
            return false;
        }
        *quantum_us = (uint64_t)us;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "growth"))) {
        if (!kairos_is_count(p->value) || p->value > 1000) {
            priority_policy_string_dup(err, "plas: growth must be a whole number between 1 and 1000");
            return false;
        }
        *growth = (uint32_t)p->value;
    }
    if ((p = kairos_param_find(params->ptr, params->len, "beta"))) {
        if (!kairos_is_real(p->value, 0.0) || p->value <= 0.0) {
            priority_policy_string_dup(err, "plas: beta must be a finite number > 0");
            return false;
        }
        *beta = p->value;
    }
    return true;
}

bool exports_kairos_policy_priority_rank(uint64_t now_us,
                                         exports_kairos_policy_priority_pending_columns_t *pending,
                                         exports_kairos_policy_priority_list_param_t *params,
                                         exports_kairos_policy_priority_ranking_t *ret,
                                         priority_policy_string_t *err) {
    (void)now_us;
    uint32_t queues = 8, growth = 2;
    uint64_t quantum_us = 1000000;
    double beta = 8.0;
    bool ok = read_params(params, &queues, &quantum_us, &growth, &beta, err);
    if (ok) {
        uint64_t thresholds[MAX_QUEUES];
        uint32_t n_thresholds = 0;
        uint64_t width = quantum_us > 1 ? quantum_us : 1, total = 0;
        for (uint32_t i = 1; i < (queues > 1 ? queues : 1); i++) {
            total = sat_add(total, width);
            thresholds[n_thresholds++] = total;
            width = sat_mul(width, growth > 1 ? growth : 1);
        }
        uint64_t floor_q = quantum_us > 1 ? quantum_us : 1;
        size_t n = pending->request.len;
        const uint64_t *service_ns = pending->attained_service_ns.ptr;
        const uint64_t *queued_ns = pending->queued_ns.ptr;
        uint64_t *major = kairos_u64s(n);
        for (size_t i = 0; i < n; i++) {
            uint64_t service = service_ns[i] / 1000;
            double queued = (double)(queued_ns[i] / 1000);
            double floor_s = (double)(service > floor_q ? service : floor_q);
            uint64_t queue = 0;
            if (!(queued >= beta * floor_s)) {
                while (queue < n_thresholds && thresholds[queue] <= service) queue++;
            }
            major[i] = queue;
        }
        *ret = (exports_kairos_policy_priority_ranking_t){
            .tag = EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_KEYS,
            .val.keys.major = {major, n},
        };
    }
    exports_kairos_policy_priority_pending_columns_free(pending);
    exports_kairos_policy_priority_list_param_free(params);
    return ok;
}

void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary) {
    (void)summary;
}
