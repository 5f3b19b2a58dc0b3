/*
 * Contact-aware: execute the chunk through free-space transit and hand control back just
 * before the chunk's plan reaches a contact (it slows down, or switches the gripper), as a
 * horizon-policy plugin.
 *
 * Twin of the server's native `contact` policy (server/src/horizon/contact.rs); it gives the
 * same answer bit for bit (checked by server/tests/it/plugin_twins.rs), over the final actions
 * A[s][n][d] of the S samples, D = action dimension, in double widened from float, no fused
 * multiply-add:
 *   1. speed_n = sqrt(sum over d < D-1 of A[0][n][d]^2), dimension order (0 when D = 1).
 *   2. event = the first n >= 0 with !(speed_n >= slow) (a NaN counts as slow), or with n >= 1
 *      and (A[0][n][D-1] > 0) != (A[0][n-1][D-1] > 0) (the gripper switches), or N.
 *   3. prefix = event - margin if event > margin, else 0.
 *   4. Only with param release = R: sample s plans a release if A[s][0][D-1] > 0 and
 *      !(A[s][n][D-1] > 0) for some 1 <= n <= min(R, N - 1) (a NaN counts as open); if at
 *      least quorum samples do, prefix = max(prefix, R) (execute through the release).
 *   5. H = min(max(prefix, h_min), h_max), h_min = max(context h-min, param h_min),
 *      h_max = min(context h-max, N, param h_max); a param h_max below h_min is raised to it.
 * Parameters: slow (real >= 0, default 0.5), margin (whole number >= 0, default 1),
 * h_min and h_max (whole numbers >= 1, optional), release (whole number >= 1, optional) and
 * quorum (whole number >= 1, default 1); checked in that order.
 */
#include "horizon_policy.h"
#include "kairos_policy.h"
#include "cut_rule.h"

#define DEFAULT_SLOW 0.5
#define DEFAULT_MARGIN 1u
#define DEFAULT_QUORUM 1u

static uint32_t first_contact(const exports_kairos_policy_horizon_chunk_t *c, double slow) {
    uint32_t n_len = c->chunk_len, d = c->action_dim;
    const float *a = c->actions.ptr; /* sample 0 */
    for (uint32_t n = 0; n < n_len; n++) {
        const float *cur = a + (size_t)n * d;
        double acc = 0.0;
        for (uint32_t i = 0; i + 1 < d; i++) {
            double x = (double)cur[i];
            acc += x * x;
        }
        if (!(sqrt(acc) >= slow)) return n;
        if (n >= 1) {
            const float *prev = cur - d;
            if ((cur[d - 1] > 0.0f) != (prev[d - 1] > 0.0f)) return n;
        }
    }
    return n_len;
}

/* Step 4: checks release and quorum; *lower = R when quorum samples plan a release. */
static bool release_floor(const exports_kairos_policy_horizon_chunk_t *c,
                          const exports_kairos_policy_horizon_list_param_t *params, uint32_t *lower,
                          horizon_error_t *err) {
    uint32_t release, quorum;
    *lower = 0;
    if (!count_param(params, "release", &release, err)) return false;
    if (!count_param(params, "quorum", &quorum, err)) return false;
    if (release == 0) return true;
    if (quorum == 0) quorum = DEFAULT_QUORUM;
    uint32_t n_len = c->chunk_len, d = c->action_dim;
    /* An empty chunk plans nothing (and the host refuses it after this, as the native does). */
    if (n_len == 0 || d == 0) return true;
    uint32_t last = release < n_len - 1 ? release : n_len - 1;
    uint32_t votes = 0;
    for (uint32_t s = 0; s < c->samples; s++) {
        const float *a = c->actions.ptr + (size_t)s * n_len * d;
        if (!(a[d - 1] > 0.0f)) continue;
        for (uint32_t n = 1; n <= last; n++) {
            if (!(a[(size_t)n * d + d - 1] > 0.0f)) {
                votes++;
                break;
            }
        }
    }
    if (votes >= quorum) *lower = release;
    return true;
}

static const char *const KNOWN[] = {"h_max", "h_min", "margin", "quorum", "release", "slow", NULL};
static const cut_rule_t RULE = {"slow", DEFAULT_SLOW, DEFAULT_MARGIN, KNOWN, "unknown parameter (expected one of: slow, margin, h_min, h_max, release, quorum)", first_contact, release_floor};

CUT_RULE_EXPORT(RULE)
