/*
 * The load-aware horizon: the §3.1 threshold rule, lengthened by the actions the server's
 * backlog lasts, so a robot keeps executing instead of stalling while its next request queues.
 * Needs kairos:policy@0.3.0 (the context's `load`).
 *
 * Twin of the server's native `load-aware` policy (server/src/horizon/load_aware.rs); it gives
 * the same answer bit for bit (checked by server/tests/it/plugin_twins.rs):
 *   1. H_thresh = the threshold rule's steps 1-4 with t (threshold_rule.h).
 *   2. extra = 0 without a load. Otherwise, in double, no fused multiply-add:
 *      x = (gain * (backlog_ns / 1e9)) * control_hz; extra = 0 if !(x > 0),
 *      UINT32_MAX if x >= 4294967295, else ceil(x).
 *   3. H = min(max(H_thresh + extra, h_min), h_max) (saturating add), h_min and h_max as the
 *      threshold rule's step 5.
 * Parameters: t (real >= 0, default 0.4), h_min (whole number >= 1, optional), gain (real >= 0,
 * default 1).
 */
#include "horizon_policy.h"
#include "kairos_policy.h"
#include "threshold_rule.h"

#define DEFAULT_T 0.4
#define DEFAULT_GAIN 1.0

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

static void param_error(horizon_error_t *err, const kairos_policy_types_param_t *p, const char *reason) {
    err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
    horizon_policy_string_dup_n(&err->val.invalid_param.name, (const char *)p->name.ptr, p->name.len);
    horizon_policy_string_dup(&err->val.invalid_param.reason, reason);
}

/* Step 2. */
static uint32_t extra_actions(const exports_kairos_policy_horizon_horizon_context_t *ctx, double gain) {
    if (!ctx->load.is_some) return 0;
    double backlog_ns = (double)ctx->load.val.backlog_ns;
    double x = (gain * (backlog_ns / 1e9)) * (double)ctx->control_hz;
    if (!(x > 0.0)) return 0;
    if (x >= 4294967295.0) return UINT32_MAX;
    return (uint32_t)ceil(x);
}

static bool decide(exports_kairos_policy_horizon_chunk_t *chunk,
                   exports_kairos_policy_horizon_horizon_context_t *ctx,
                   exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                   horizon_error_t *err) {
    static const char *const known[] = {"t", "h_min", "gain", NULL};
    const kairos_policy_types_param_t *unknown = kairos_param_unknown(params->ptr, params->len, known);
    if (unknown) {
        param_error(err, unknown, "unknown parameter (expected one of: t, h_min, gain)");
        return false;
    }
    double t = DEFAULT_T, gain = DEFAULT_GAIN;
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
    p = kairos_param_find(params->ptr, params->len, "gain");
    if (p) {
        if (!kairos_is_real(p->value, 0.0)) {
            param_error(err, p, "not a finite number >= 0");
            return false;
        }
        gain = p->value;
    }
    uint32_t h_max = ctx->h_max < chunk->chunk_len ? ctx->h_max : chunk->chunk_len;
    if (ctx->h_min == 0 || ctx->h_min > h_max) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_UNSUPPORTED;
        horizon_policy_string_dup(&err->val.unsupported, "no horizon satisfies 1 <= h_min <= h_max");
        return false;
    }
    uint32_t h_min = ctx->h_min > extra_min ? ctx->h_min : extra_min;
    if (h_min > h_max) h_min = h_max;
    uint32_t h = threshold_prefix(chunk, t, 0 /* the final step */);
    uint32_t extra = extra_actions(ctx, gain);
    h = h > UINT32_MAX - extra ? UINT32_MAX : h + extra;
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
