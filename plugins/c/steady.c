/*
 * Steady motion: execute the chunk while its actions keep doing the same thing, and hand
 * control back a little before the chunk changes course, as a horizon-policy plugin.
 *
 * Twin of the server's native `steady` policy (server/src/horizon/steady.rs); it gives the same
 * answer bit for bit (checked by server/tests/it/plugin_twins.rs), over the final actions
 * A[0][n][d] of sample 0, in double widened from float, no fused multiply-add:
 *   1. For n >= 1, jump_n = sqrt(sum over d of (A[0][n][d] - A[0][n-1][d])^2), dimension order.
 *   2. change = the first n >= 1 with !(jump_n <= delta) (a NaN counts as a change), or N.
 *   3. prefix = change - margin if change > margin, else 0.
 *   4. H = min(max(prefix, h_min), h_max), h_min = max(context h-min, param h_min),
 *      h_max = min(context h-max, N, param h_max); a param h_max below h_min is raised to it.
 * Parameters: delta (real >= 0, default 0.25), margin (whole number >= 0, default 1),
 * h_min and h_max (whole numbers >= 1, optional).
 */
#include "horizon_policy.h"
#include "kairos_policy.h"
#include "cut_rule.h"

#define DEFAULT_DELTA 0.25
#define DEFAULT_MARGIN 1u

static uint32_t first_change(const exports_kairos_policy_horizon_chunk_t *c, double delta) {
    uint32_t n_len = c->chunk_len, d = c->action_dim;
    const float *a = c->actions.ptr; /* sample 0 */
    for (uint32_t n = 1; n < n_len; n++) {
        const float *prev = a + (size_t)(n - 1) * d, *cur = a + (size_t)n * d;
        double acc = 0.0;
        for (uint32_t i = 0; i < d; i++) {
            double x = (double)cur[i] - (double)prev[i];
            acc += x * x;
        }
        if (!(sqrt(acc) <= delta)) return n;
    }
    return n_len;
}

static const char *const KNOWN[] = {"delta", "h_max", "h_min", "margin", NULL};
static const cut_rule_t RULE = {"delta", DEFAULT_DELTA, DEFAULT_MARGIN, KNOWN, "unknown parameter (expected one of: delta, margin, h_min, h_max)", first_change, NULL};

CUT_RULE_EXPORT(RULE)
