/*
 * The paper's §3.1 threshold rule, steps 1-4 (server/src/horizon/threshold.rs,
 * `threshold_prefix`, with the step it reads): shared by the plugins that build on it (threshold.c, load_aware.c).
 * Include after the world's generated header; the chunk type is the same in every version.
 */
#ifndef KAIROS_THRESHOLD_RULE_H
#define KAIROS_THRESHOLD_RULE_H

static double l2(const float *v, uint32_t d) {
    double acc = 0.0;
    for (uint32_t i = 0; i < d; i++) {
        double x = (double)v[i];
        acc += x * x;
    }
    return sqrt(acc);
}

/* step == 0: the final step. */
static uint32_t threshold_prefix(const exports_kairos_policy_horizon_chunk_t *c, double t, uint32_t step) {
    uint32_t k = c->steps, n_len = c->chunk_len, d = c->action_dim;
    if (k < 2) return n_len;
    uint32_t read = (step == 0 || step > k - 1) ? k - 1 : step;
    double bound = 1.0 + t;
    size_t step_stride = (size_t)n_len * d;
    for (uint32_t n = 0; n < n_len; n++) {
        const float *u = c->updates.ptr + (size_t)n * d; /* sample 0, step 0, action n */
        double sum = 0.0;
        for (uint32_t s = 0; s < read; s++) sum += l2(u + s * step_stride, d);
        double mean = sum / (double)read;
        double last = l2(u + (size_t)read * step_stride, d);
        if (!(last <= bound * mean)) return n;
    }
    return n_len;
}

#endif
