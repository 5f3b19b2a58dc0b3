/*
 * Template: a horizon-policy plugin in C.
 *
 * "bound": execute the prefix of the chunk whose final-step updates are all at most `bound`
 * (an absolute L2 norm), clamped to the robot's [h-min, h-max]. Parameter: bound (default
 * 0.05, finite >= 0). The same policy is in templates/python/app.py and
 * examples/bound_horizon.rs.
 *
 * Build (templates/c/build.sh does exactly this):
 *   clang --target=wasm32-wasi -O2 -ffp-contract=off -mexec-model=reactor -Wl,--strip-all \
 *     -I SDK/since_v0.2.0 -I SDK -o bound.core.wasm bound.c \
 *     SDK/since_v0.2.0/horizon_policy.c SDK/kairos_world_stub.c
 *   kairos plugin componentize bound.core.wasm --world horizon -o bound.wasm
 *   kairos plugin check bound.wasm --param bound=0.05
 * where SDK is sdk/guest/c. Debian/Ubuntu: apt-get install clang lld wasi-libc
 * libclang-rt-dev-wasm32.
 *
 * Rules of the generated bindings: the function receives ownership of its arguments (free
 * them), and strings in an error must be allocated (horizon_policy_string_dup). No printf,
 * files or clocks: a plugin that imports WASI is refused by `componentize`.
 */
#include <math.h>

#include "horizon_policy.h"
#include "kairos_policy.h"

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

static bool decide(const exports_kairos_policy_horizon_chunk_t *chunk,
                   const exports_kairos_policy_horizon_horizon_context_t *ctx,
                   const exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                   horizon_error_t *err) {
    static const char *const known[] = {"bound", NULL};
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (p) {
        err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
        horizon_policy_string_dup_n(&err->val.invalid_param.name, (const char *)p->name.ptr, p->name.len);
        horizon_policy_string_dup(&err->val.invalid_param.reason, "unknown parameter (expected: bound)");
        return false;
    }
    double bound = 0.05;
    if ((p = kairos_param_find(params->ptr, params->len, "bound"))) {
        if (!kairos_is_real(p->value, 0.0)) {
            err->tag = EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM;
            horizon_policy_string_dup(&err->val.invalid_param.name, "bound");
            horizon_policy_string_dup(&err->val.invalid_param.reason, "not a finite number >= 0");
            return false;
        }
        bound = p->value;
    }
    uint32_t n_len = chunk->chunk_len, d = chunk->action_dim;
    /* Sample 0, last step: updates[((0 * K + K-1) * N + n) * D ..]. */
    const float *last = chunk->updates.ptr + (size_t)(chunk->steps - 1) * n_len * d;
    uint32_t h = 0;
    while (h < n_len) {
        double acc = 0.0;
        for (uint32_t j = 0; j < d; j++) acc += (double)last[(size_t)h * d + j] * last[(size_t)h * d + j];
        if (!(sqrt(acc) <= bound)) break;
        h++;
    }
    if (h < ctx->h_min) h = ctx->h_min;
    if (h > ctx->h_max) h = ctx->h_max;
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
