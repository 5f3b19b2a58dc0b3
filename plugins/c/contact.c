/*
 * Contact-aware: execute the chunk through free-space transit and hand control back just
 * before the chunk's plan reaches a contact (it slows down, or switches the gripper), as a
 * horizon-policy plugin.
 *
 * Twin of the server's native `contact` policy (server/src/horizon/contact.rs); it gives the
 * same answer bit for bit (checked by server/tests/it/plugin_twins.rs), over the final actions
 * A[0][n][d] of sample 0, D = action dimension, in double widened from float, no fused
 * multiply-add:
 *   1. speed_n = sqrt(sum over d < D-1 of A[0][n][d]^2), dimension order (0 when D = 1).
 *   2. event = the first n >= 0 with !(speed_n >= slow) (a NaN counts as slow), or with n >= 1
 *      and (A[0][n][D-1] > 0) != (A[0][n-1][D-1] > 0) (the gripper switches), or N.
 *   3. prefix = event - margin if event > margin, else 0.
 *   4. H = min(max(prefix, h_min), h_max), h_min = max(context h-min, param h_min),
 *      h_max = min(context h-max, N, param h_max); a param h_max below h_min is raised to it.
 * Parameters: slow (real >= 0, default 0.5), margin (whole number >= 0, default 1),
 * h_min and h_max (whole numbers >= 1, optional).
 */
#include "horizon_policy.h"
#include "kairos_policy.h"

#define DEFAULT_SLOW 0.5
#define DEFAULT_MARGIN 1u

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

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

static void param_error(horizon_error_t *err, const kairos_policy_types_param_t *p, const char *reason) {
    err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
    horizon_policy_string_dup_n(&err->val.invalid_param.name, (const char *)p->name.ptr, p->name.len);
    horizon_policy_string_dup(&err->val.invalid_param.reason, reason);
}

/* A whole-number parameter >= 1 into *out (0 when absent); false after setting *err. */
static bool count_param(const exports_kairos_policy_horizon_list_param_t *params, const char *name,
                        uint32_t *out, horizon_error_t *err) {
    const kairos_policy_types_param_t *p = kairos_param_find(params->ptr, params->len, name);
    *out = 0;
    if (!p) return true;
    if (!kairos_is_count(p->value)) {
        param_error(err, p, "not a whole number of actions >= 1");
        return false;
    }
    *out = (uint32_t)p->value;
    return true;
}

static bool decide(exports_kairos_policy_horizon_chunk_t *chunk,
                   exports_kairos_policy_horizon_horizon_context_t *ctx,
                   exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                   horizon_error_t *err) {
    static const char *const known[] = {"h_max", "h_min", "margin", "slow", NULL};
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (p) {
        param_error(err, p, "unknown parameter (expected one of: slow, margin, h_min, h_max)");
        return false;
    }
    /* Checked in the native policy's order: margin, slow, h_min, h_max. */
    uint32_t margin = DEFAULT_MARGIN;
    p = kairos_param_find(params->ptr, params->len, "margin");
    if (p) {
        if (!(isfinite(p->value) && p->value >= 0.0 && p->value == trunc(p->value) && p->value <= 1e9)) {
            param_error(err, p, "not a whole number of actions >= 0");
            return false;
        }
        margin = (uint32_t)p->value;
    }
    double slow = DEFAULT_SLOW;
    p = kairos_param_find(params->ptr, params->len, "slow");
    if (p) {
        if (!kairos_is_real(p->value, 0.0)) {
            param_error(err, p, "not a finite number >= 0");
            return false;
        }
        slow = p->value;
    }
    uint32_t extra_min, cap;
    if (!count_param(params, "h_min", &extra_min, err)) return false;
    if (!count_param(params, "h_max", &cap, err)) return false;
    uint32_t h_max = ctx->h_max;
    if (cap != 0) {
        uint32_t floor = ctx->h_min > extra_min ? ctx->h_min : extra_min;
        uint32_t raised = cap > floor ? cap : floor;
        if (raised < h_max) h_max = raised;
    }
    if (chunk->chunk_len < h_max) h_max = chunk->chunk_len;
    if (ctx->h_min == 0 || ctx->h_min > h_max) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_UNSUPPORTED;
        horizon_policy_string_dup(&err->val.unsupported, "no horizon satisfies 1 <= h_min <= h_max");
        return false;
    }
    uint32_t h_min = ctx->h_min > extra_min ? ctx->h_min : extra_min;
    if (h_min > h_max) h_min = h_max;
    uint32_t event = first_contact(chunk, slow);
    uint32_t h = event > margin ? event - margin : 0;
    if (h < h_min) h = h_min;
    if (h > h_max) h = h_max;
    *ret = h;
    return true;
}

bool exports_kairos_policy_horizon_choose(exports_kairos_policy_horizon_chunk_t *chunk,
                                          exports_kairos_policy_horizon_horizon_context_t *ctx,
                                          exports_kairos_policy_horizon_list_param_t *params,
                                          uint32_t *ret, horizon_error_t *err) {
    bool ok = decide(chunk, ctx, params, ret, err);
    /* The arguments belong to the callee. */
    exports_kairos_policy_horizon_chunk_free(chunk);
    exports_kairos_policy_horizon_horizon_context_free(ctx);
    exports_kairos_policy_horizon_list_param_free(params);
    return ok;
}
