// Written by hand after `wit-bindgen` 0.60.0 (c) for kairos:policy@0.3.0: the 0.2.0 bindings
// plus `server-load` and the context's `load` (wit-bindgen-cli was not available when 0.3.0 was
// added; regenerate with regen-bindings.sh and diff). Checked by the load-aware twin test.
#ifndef __BINDINGS_HORIZON_POLICY_H
#define __BINDINGS_HORIZON_POLICY_H
#ifdef __cplusplus
extern "C" {
#endif

#include <stdint.h>
#include <stdbool.h>
#include <stddef.h>

typedef struct horizon_policy_string_t {
  uint8_t*ptr;
  size_t len;
} horizon_policy_string_t;

// One user parameter of a policy, e.g. `t = 0.4` for the threshold horizon policy.
// 
// Parameters come from the robot's request (horizon policies) or from the server's
// configuration (priority policies). They arrive sorted by name, each name once.
typedef struct kairos_policy_types_param_t {
  // Parameter name, e.g. `t`.
  horizon_policy_string_t   name;
  // Its value. Integer parameters are passed as whole numbers.
  double   value;
} kairos_policy_types_param_t;

// A parameter the policy cannot work with.
typedef struct kairos_policy_types_param_problem_t {
  // Which parameter.
  horizon_policy_string_t   name;
  // What is wrong with it (missing, out of range, ...), for the server's log.
  horizon_policy_string_t   reason;
} kairos_policy_types_param_problem_t;

typedef kairos_policy_types_param_t exports_kairos_policy_horizon_param_t;

typedef kairos_policy_types_param_problem_t exports_kairos_policy_horizon_param_problem_t;

typedef struct {
  float *ptr;
  size_t len;
} horizon_policy_list_f32_t;

// One generated action chunk and the diffusion updates that produced it.
// 
// The model ran `steps` refinement steps (`K`); at each step it applied an update of
// `action-dim` values (`D`) to every one of the `chunk-len` actions (`N`). When the robot
// asked for several samples of the same observation (`samples` = `S` > 1), each sample is
// a full chunk drawn with different noise; sample 0 is the chunk the robot will execute.
// 
// Both lists are flat and row-major:
// - `updates` has `S * K * N * D` values; the update that step `k` applied to action `n`
//   of sample `s` starts at index `((s * K + k) * N + n) * D`;
// - `actions` has `S * N * D` values; action `n` of sample `s` starts at `(s * N + n) * D`.
// 
// The server guarantees every dimension is at least 1 and both lengths are exact.
typedef struct exports_kairos_policy_horizon_chunk_t {
  // `S`: samples drawn for this observation (1 unless the request asked for more).
  uint32_t   samples;
  // `K`: refinement (denoising) steps.
  uint32_t   steps;
  // `N`: actions per chunk.
  uint32_t   chunk_len;
  // `D`: values per action.
  uint32_t   action_dim;
  // `[S][K][N][D]` per-step updates `U`.
  horizon_policy_list_f32_t   updates;
  // `[S][N][D]` final actions.
  horizon_policy_list_f32_t   actions;
} exports_kairos_policy_horizon_chunk_t;

typedef struct {
  uint32_t *ptr;
  size_t len;
} horizon_policy_list_u32_t;

// The server's load when the chunk's forward pass ended, as its scheduler knows it at the
// horizon decision (the same numbers for every chunk of one batch).
typedef struct exports_kairos_policy_horizon_server_load_t {
  // Requests waiting for dispatch (received, not yet in a batch).
  uint32_t   queued;
  // Requests in batches the engines are still running (this chunk's batch excluded: its
  // forward pass has ended).
  uint32_t   running;
  // Tasks open on the server: robots it is serving.
  uint32_t   open_tasks;
  // The work in hand, in time: when an engine would next be free if no new request
  // came. A request sent now waits about this long before its forward pass starts.
  // 0 when an engine is free and nothing is queued.
  uint64_t   backlog_ns;
} exports_kairos_policy_horizon_server_load_t;

typedef struct exports_kairos_policy_horizon_option_server_load_t {
  bool is_some;
  exports_kairos_policy_horizon_server_load_t val;
} exports_kairos_policy_horizon_option_server_load_t;

// Everything a horizon policy may base its decision on, besides the chunk.
typedef struct exports_kairos_policy_horizon_horizon_context_t {
  // Smallest horizon the robot accepts (`H_min` in §3.1); at least 1.
  uint32_t   h_min;
  // Largest horizon the robot accepts; `h-min <= h-max <= chunk-len`.
  uint32_t   h_max;
  // The robot's control frequency in actions per second.
  float   control_hz;
  // Index of this round within its task (0 for the task's first chunk).
  uint64_t   round_index;
  // Horizons chosen for this task's most recent rounds, oldest first (bounded, may be
  // empty).
  horizon_policy_list_u32_t   recent_horizons;
  // The server's load; `none` where there is no server (trace generation, a conformance
  // case that leaves it out): a policy must then decide from the chunk alone.
  exports_kairos_policy_horizon_option_server_load_t   load;
} exports_kairos_policy_horizon_horizon_context_t;

// Why a policy could not decide. The server then uses its built-in fallback policy for
// this round and logs the reason.
typedef struct exports_kairos_policy_horizon_horizon_error_t {
  uint8_t tag;
  union {
    exports_kairos_policy_horizon_param_problem_t     invalid_param;
    horizon_policy_string_t     unsupported;
    horizon_policy_string_t     failed;
  } val;
} exports_kairos_policy_horizon_horizon_error_t;

// A parameter is missing or out of range.
#define EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_INVALID_PARAM 0
// The input lacks what the policy needs (e.g. a spread policy given one sample).
#define EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_UNSUPPORTED 1
// Any other failure.
#define EXPORTS_KAIROS_POLICY_HORIZON_HORIZON_ERROR_FAILED 2

typedef struct {
  exports_kairos_policy_horizon_param_t *ptr;
  size_t len;
} exports_kairos_policy_horizon_list_param_t;

typedef struct {
  bool is_err;
  union {
    uint32_t ok;
    exports_kairos_policy_horizon_horizon_error_t err;
  } val;
} exports_kairos_policy_horizon_result_u32_horizon_error_t;

// Exported Functions from `kairos:policy/horizon@0.3.0`
bool exports_kairos_policy_horizon_choose(exports_kairos_policy_horizon_chunk_t *chunk, exports_kairos_policy_horizon_horizon_context_t *context, exports_kairos_policy_horizon_list_param_t *params, uint32_t *ret, exports_kairos_policy_horizon_horizon_error_t *err);

// Helper Functions

void kairos_policy_types_param_free(kairos_policy_types_param_t *ptr);

void kairos_policy_types_param_problem_free(kairos_policy_types_param_problem_t *ptr);

void exports_kairos_policy_horizon_param_free(exports_kairos_policy_horizon_param_t *ptr);

void exports_kairos_policy_horizon_param_problem_free(exports_kairos_policy_horizon_param_problem_t *ptr);

void horizon_policy_list_f32_free(horizon_policy_list_f32_t *ptr);

void exports_kairos_policy_horizon_chunk_free(exports_kairos_policy_horizon_chunk_t *ptr);

void horizon_policy_list_u32_free(horizon_policy_list_u32_t *ptr);

void exports_kairos_policy_horizon_horizon_context_free(exports_kairos_policy_horizon_horizon_context_t *ptr);

void exports_kairos_policy_horizon_horizon_error_free(exports_kairos_policy_horizon_horizon_error_t *ptr);

void exports_kairos_policy_horizon_list_param_free(exports_kairos_policy_horizon_list_param_t *ptr);

void exports_kairos_policy_horizon_result_u32_horizon_error_free(exports_kairos_policy_horizon_result_u32_horizon_error_t *ptr);

// Sets the string `ret` to reference the input string `s` without copying it
void horizon_policy_string_set(horizon_policy_string_t *ret, const char*s);

// Creates a copy of the input nul-terminated string `s` and
// stores it into the component model string `ret`.
void horizon_policy_string_dup(horizon_policy_string_t *ret, const char*s);

// Creates a copy of the input string `s` with length `len` and
// stores it into the component model string `ret`.
// The length is specified in code units (bytes for UTF-8, 16-bit values for UTF-16).
void horizon_policy_string_dup_n(horizon_policy_string_t *ret, const char*s, size_t len);

// Deallocates the string pointed to by `ret`, deallocating
// the memory behind the string.
void horizon_policy_string_free(horizon_policy_string_t *ret);

#ifdef __cplusplus
}
#endif
#endif
