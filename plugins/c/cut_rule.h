/*
 * Steps 3-4 of the "cut before an event" horizon rules (server/src/horizon/steady.rs and
 * contact.rs, `clamp_with_cap`), with their parameter checks: shared by steady.c and contact.c.
 * A rule supplies its event (the first action of the chunk that changes course, or plans a
 * contact), its real parameter and optionally a floor on the prefix with its own parameters
 * (contact's `release`); this cuts `margin` actions before the event, raises the result to the
 * floor and clamps to
 * [max(context h-min, param h_min), min(context h-max, N, param h_max)] (a param h_max below
 * h_min is raised to it). Include after the world's generated header and kairos_policy.h.
 */
#ifndef KAIROS_CUT_RULE_H
#define KAIROS_CUT_RULE_H

typedef exports_kairos_policy_horizon_horizon_error_t horizon_error_t;

typedef struct {
    const char *real;           /* the real parameter's name (delta, slow) */
    double real_default;
    uint32_t margin_default;
    const char *const *known;   /* every parameter name, NULL-terminated */
    const char *unknown;        /* the error reason for an unknown name */
    uint32_t (*event)(const exports_kairos_policy_horizon_chunk_t *c, double real);
    /* Optional (NULL: none): checks the rule's own parameters, after the shared ones, and sets
     * *lower, a lower bound on the prefix (0: none); false after setting *err. */
    bool (*floor)(const exports_kairos_policy_horizon_chunk_t *c,
                  const exports_kairos_policy_horizon_list_param_t *params, uint32_t *lower,
                  horizon_error_t *err);
} cut_rule_t;

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

/* Steps 3-4 for `rule`, after checking the parameters. */
static bool cut_decide(const cut_rule_t *rule, exports_kairos_policy_horizon_chunk_t *chunk,
                       exports_kairos_policy_horizon_horizon_context_t *ctx,
                       exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret,
                       horizon_error_t *err) {
    const char *const *known = rule->known;
    const kairos_policy_types_param_t *p = kairos_param_unknown(params->ptr, params->len, known);
    if (p) {
        param_error(err, p, rule->unknown);
        return false;
    }
    /* Checked in the native policies' order: margin, the real parameter, h_min, h_max. */
    uint32_t margin = rule->margin_default;
    p = kairos_param_find(params->ptr, params->len, "margin");
    if (p) {
        if (!(isfinite(p->value) && p->value >= 0.0 && p->value == trunc(p->value) && p->value <= 1e9)) {
            param_error(err, p, "not a whole number of actions >= 0");
            return false;
        }
        margin = (uint32_t)p->value;
    }
    double real = rule->real_default;
    p = kairos_param_find(params->ptr, params->len, rule->real);
    if (p) {
        if (!kairos_is_real(p->value, 0.0)) {
            param_error(err, p, "not a finite number >= 0");
            return false;
        }
        real = p->value;
    }
    uint32_t extra_min, cap, lower = 0;
    if (!count_param(params, "h_min", &extra_min, err)) return false;
    if (!count_param(params, "h_max", &cap, err)) return false;
    if (rule->floor && !rule->floor(chunk, params, &lower, err)) return false;
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
    uint32_t event = rule->event(chunk, real);
    uint32_t h = event > margin ? event - margin : 0;
    if (h < lower) h = lower;
    if (h < h_min) h = h_min;
    if (h > h_max) h = h_max;
    *ret = h;
    return true;
}

/* The world's export for a rule: decide, then free the arguments, which belong to the callee.
 * A rule's source ends with `CUT_RULE_EXPORT(RULE)`. */
#define CUT_RULE_EXPORT(rule)                                                                      \
    bool exports_kairos_policy_horizon_choose(                                                     \
        exports_kairos_policy_horizon_chunk_t *chunk,                                              \
        exports_kairos_policy_horizon_horizon_context_t *ctx,                                      \
        exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret, horizon_error_t *err) { \
        bool ok = cut_decide(&(rule), chunk, ctx, params, ret, err);                               \
        exports_kairos_policy_horizon_chunk_free(chunk);                                           \
        exports_kairos_policy_horizon_horizon_context_free(ctx);                                   \
        exports_kairos_policy_horizon_list_param_free(params);                                     \
        return ok;                                                                                 \
    }

#endif
