/*
 * The static horizon: execute h actions every round, whatever the chunk says.
 *
 * Twin of the server's native `static` policy (server/src/horizon/fixed.rs):
 *   H = min(max(h, h-min), h_max) with h_max = min(context h-max, N).
 * Parameter: h (whole number >= 1, required).
 */
#include "horizon_policy.h"
#include "kairos_policy.h"

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

static bool decide(exports_kairos_policy_horizon_chunk_t *chunk,
                   exports_kairos_policy_horizon_horizon_context_t *ctx,
                   exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                   horizon_error_t *err) {
    static const char *const known[] = {"h", NULL};
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (!p) p = kairos_param_find(params->ptr, params->len, "h");
    if (!p || !kairos_param_is(p, "h") || !kairos_is_count(p->value)) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
        if (p) {
            horizon_policy_string_dup_n(&err->val.invalid_param.name, (const char *)p->name.ptr, p->name.len);
        } else {
            horizon_policy_string_dup(&err->val.invalid_param.name, "h");
        }
        horizon_policy_string_dup(&err->val.invalid_param.reason,
                                  !p ? "required: the number of actions to execute per round"
                                     : !kairos_param_is(p, "h") ? "unknown parameter (expected one of: h)"
                                                                : "not a whole number of actions >= 1");
        return false;
    }
    uint32_t h = p->value > 4294967295.0 ? UINT32_MAX : (uint32_t)p->value;
    uint32_t h_max = ctx->h_max < chunk->chunk_len ? ctx->h_max : chunk->chunk_len;
    if (ctx->h_min == 0 || ctx->h_min > h_max) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_UNSUPPORTED;
        horizon_policy_string_dup(&err->val.unsupported, "no horizon satisfies 1 <= h_min <= h_max");
        return false;
    }
    if (h < ctx->h_min) h = ctx->h_min;
    if (h > h_max) h = h_max;
    *ret = h;
    return true;
}

bool exports_kairos_policy_horizon_choose(exports_kairos_policy_horizon_chunk_t *chunk,
                                          exports_kairos_policy_horizon_horizon_context_t *ctx,
                                          exports_kairos_policy_horizon_list_param_t *params,
                                          uint32_t *ret, horizon_error_t *err) {
    bool ok = decide(chunk, ctx, params, ret, err);
    exports_kairos_policy_horizon_chunk_free(chunk);
    exports_kairos_policy_horizon_horizon_context_free(ctx);
    exports_kairos_policy_horizon_list_param_free(params);
    return ok;
}
