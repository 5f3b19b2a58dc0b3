/*
 * The paper's confidence-threshold horizon policy (§3.1), as a horizon-policy plugin.
 *
 * Twin of the server's native `threshold` policy (server/src/horizon/threshold.rs); it gives
 * the same answer bit for bit (checked by server/tests/plugin_twins.rs):
 *   1. Only sample 0 is used. ||U[0][k][n]|| is the L2 norm over the D values, accumulated in
 *      double in dimension order (no fused multiply-add), then sqrt.
 *   2. The step read is r = min(step, K-1) (step defaults to K-1, the final step).
 *      mean_n = (sum over k = 0..r-1 of ||U[0][k][n]||) / r, summed in step order.
 *   3. Action n exceeds iff !(||U[0][r][n]|| <= (1+t) * mean_n): a NaN counts as unconverged.
 *      With K = 1 no action exceeds.
 *   4. H_thresh = index of the first exceeding action, or N if none exceeds.
 *   5. H = min(max(H_thresh, h_min), h_max), h_min = max(context h-min, param h_min),
 *      h_max = min(context h-max, N).
 * Parameters: t (real >= 0, default 0.4), h_min (whole number >= 1, optional), step (whole
 * number >= 1, optional: the 0-based denoising step whose update is read).
 */
#include "horizon_policy.h"
#include "kairos_policy.h"
#include "threshold_rule.h"

#define DEFAULT_T 0.4

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

static void param_error(horizon_error_t *err, const kairos_policy_types_param_t *p, const char *reason) {
    err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
    horizon_policy_string_dup_n(&err->val.invalid_param.name, (const char *)p->name.ptr, p->name.len);
    horizon_policy_string_dup(&err->val.invalid_param.reason, reason);
}

static bool decide(exports_kairos_policy_horizon_chunk_t *chunk,
                   exports_kairos_policy_horizon_horizon_context_t *ctx,
                   exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                   horizon_error_t *err) {
    static const char *const known[] = {"h_min", "step", "t", NULL};
    const kairos_policy_types_param_t *unknown = kairos_param_unknown(params->ptr, params->len, known);
    if (unknown) {
        param_error(err, unknown, "unknown parameter (expected one of: t, h_min, step)");
        return false;
    }
    double t = DEFAULT_T;
    const kairos_policy_types_param_t *p = kairos_param_find(params->ptr, params->len, "t");
    if (p) {
        if (!kairos_is_real(p->value, 0.0)) {
            param_error(err, p, "not a finite number >= 0");
            return false;
        }
        t = p->value;
    }
    uint32_t extra_min = 0;
    p = kairos_param_find(params->ptr, params->len, "h_min");
    if (p) {
        if (!kairos_is_count(p->value)) {
            param_error(err, p, "not a whole number of actions >= 1");
            return false;
        }
        extra_min = p->value > 4294967295.0 ? UINT32_MAX : (uint32_t)p->value;
    }
    uint32_t step = 0;
    p = kairos_param_find(params->ptr, params->len, "step");
    if (p) {
        if (!kairos_is_count(p->value)) {
            param_error(err, p, "not a whole number of steps >= 1");
            return false;
        }
        step = p->value > 4294967295.0 ? UINT32_MAX : (uint32_t)p->value;
    }
    uint32_t h_max = ctx->h_max < chunk->chunk_len ? ctx->h_max : chunk->chunk_len;
    if (ctx->h_min == 0 || ctx->h_min > h_max) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_UNSUPPORTED;
        horizon_policy_string_dup(&err->val.unsupported, "no horizon satisfies 1 <= h_min <= h_max");
        return false;
    }
    uint32_t h_min = ctx->h_min > extra_min ? ctx->h_min : extra_min;
    if (h_min > h_max) h_min = h_max;
    uint32_t h = threshold_prefix(chunk, t, step);
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
