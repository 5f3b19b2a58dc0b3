// The 0.2.0 bindings with the package version 0.3.0 (the priority interface did not change);
// regenerate with regen-bindings.sh once wit-bindgen-cli 0.60.0 is at hand.
#ifndef __BINDINGS_PRIORITY_POLICY_H
#define __BINDINGS_PRIORITY_POLICY_H
#ifdef __cplusplus
extern "C" {
#endif

#include <stdint.h>
#include <stdbool.h>
#include <stddef.h>

typedef struct priority_policy_string_t {
  uint8_t*ptr;
  size_t len;
} priority_policy_string_t;

// One user parameter of a policy, e.g. `t = 0.4` for the threshold horizon policy.
// 
// Parameters come from the robot's request (horizon policies) or from the server's
// configuration (priority policies). They arrive sorted by name, each name once.
typedef struct kairos_policy_types_param_t {
  // Parameter name, e.g. `t`.
  priority_policy_string_t   name;
  // Its value. Integer parameters are passed as whole numbers.
  double   value;
} kairos_policy_types_param_t;

// A parameter the policy cannot work with.
typedef struct kairos_policy_types_param_problem_t {
  // Which parameter.
  priority_policy_string_t   name;
  // What is wrong with it (missing, out of range, ...), for the server's log.
  priority_policy_string_t   reason;
} kairos_policy_types_param_problem_t;

typedef kairos_policy_types_param_t exports_kairos_policy_priority_param_t;

// Bits of `pending-columns.present`: which optional fields a row has. A field whose bit
// is clear holds 0 in its column and means "unknown".
// 
// (A `list<flags>` would be lowered element by element; a `list<u8>` is one copy.)
// - bit 0 (`1`): `last-exec-ns`
// - bit 1 (`2`): `exec-ends-at-us`
// - bit 2 (`4`): `last-gen-ns`
// - bit 3 (`8`): `remaining-rounds`
// - bit 4 (`16`): `remaining-seconds`
typedef uint8_t exports_kairos_policy_priority_present_bits_t;

typedef struct {
  uint64_t *ptr;
  size_t len;
} priority_policy_list_u64_t;

typedef struct {
  uint32_t *ptr;
  size_t len;
} priority_policy_list_u32_t;

typedef struct {
  float *ptr;
  size_t len;
} priority_policy_list_f32_t;

typedef struct {
  exports_kairos_policy_priority_present_bits_t *ptr;
  size_t len;
} exports_kairos_policy_priority_list_present_bits_t;

// The pending round requests with their tasks' lifecycle summaries, one column per
// field. Row `i` of every column describes pending request `i`; every column has
// exactly `len(request)` rows.
typedef struct exports_kairos_policy_priority_pending_columns_t {
  // The request's id (unique for the server's lifetime).
  priority_policy_list_u64_t   request;
  // The task it belongs to.
  priority_policy_list_u64_t   task;
  // Round index within the task (0 = the task's first request).
  priority_policy_list_u64_t   round_index;
  // When the request reached the scheduler.
  priority_policy_list_u64_t   arrived_at_us;
  // When the task's first request reached the scheduler (`t_start` in Eq. 1).
  priority_policy_list_u64_t   task_started_at_us;
  // Consecutive scheduling decisions that passed this request over.
  priority_policy_list_u32_t   skipped;
  // Σ W_j: the task's wait so far by the dominant-phase rule (paper Fig. "wait_time"),
  // including the wait accrued in the round still open.
  priority_policy_list_u64_t   wait_ns;
  // Σ |G_j|: generation time the task has received (Autellix's attained service),
  // counting every finished generation of the task, answered or not.
  priority_policy_list_u64_t   attained_service_ns;
  // Σ time the task's requests spent queued before their forward pass started,
  // including this request's wait so far: execution-unaware waiting time (what
  // Autellix's anti-starvation rule uses).
  priority_policy_list_u64_t   queued_ns;
  // |E_last|: duration of the task's most recent execution phase (`present` bit 0).
  priority_policy_list_u64_t   last_exec_ns;
  // `E_last.end` as the robot reported it with this request (send time + actions
  // remaining / control frequency): when the robot runs out of actions unless this
  // request is answered (`present` bit 1; absent before the task's first execution
  // report).
  priority_policy_list_u64_t   exec_ends_at_us;
  // |G_last|: duration of the task's most recent generation phase (`present` bit 2).
  priority_policy_list_u64_t   last_gen_ns;
  // Rounds of this task already answered.
  priority_policy_list_u32_t   rounds_completed;
  // The client's estimate of the rounds its task has left, this one included
  // (`present` bit 3).
  priority_policy_list_u32_t   remaining_rounds;
  // The client's estimate of the seconds of execution its task has left (`present`
  // bit 4).
  priority_policy_list_f32_t   remaining_seconds;
  // Which optional fields each row has (see `present-bits`).
  exports_kairos_policy_priority_list_present_bits_t   present;
} exports_kairos_policy_priority_pending_columns_t;

// Sort keys, one pair per pending request (row `i` of each list belongs to request `i`).
// 
// The server dispatches by `(major, minor, arrived-at-us, request)` ascending. Either
// list may be empty, meaning all zeros: a FIFO policy returns two empty lists, a
// single-key policy an empty `minor`. Because `request` ends the key, the order is total.
typedef struct exports_kairos_policy_priority_sort_keys_t {
  // The first key, ascending.
  priority_policy_list_u64_t   major;
  // The second key, ascending, among equal `major`.
  priority_policy_list_u64_t   minor;
} exports_kairos_policy_priority_sort_keys_t;

// A policy's answer.
typedef struct exports_kairos_policy_priority_ranking_t {
  uint8_t tag;
  union {
    exports_kairos_policy_priority_sort_keys_t     keys;
    priority_policy_list_u32_t     order;
  } val;
} exports_kairos_policy_priority_ranking_t;

// Sort keys; the server sorts (the fast path: no sort in the sandbox).
#define EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_KEYS 0
// Indices into the pending rows, most urgent first: every index from 0 to
// `len(request) - 1` exactly once.
#define EXPORTS_KAIROS_POLICY_PRIORITY_RANKING_ORDER 1

// What a policy may learn from a task that ended.
typedef struct exports_kairos_policy_priority_finished_task_t {
  // The task.
  uint64_t   task;
  // Rounds it took.
  uint32_t   rounds;
  // From its first request to the end of its last execution.
  uint64_t   latency_ns;
  // Σ |G_j|.
  uint64_t   attained_service_ns;
  // Σ W_j.
  uint64_t   wait_ns;
} exports_kairos_policy_priority_finished_task_t;

typedef struct {
  exports_kairos_policy_priority_param_t *ptr;
  size_t len;
} exports_kairos_policy_priority_list_param_t;

typedef struct {
  bool is_err;
  union {
    exports_kairos_policy_priority_ranking_t ok;
    priority_policy_string_t err;
  } val;
} exports_kairos_policy_priority_result_ranking_string_t;

// Exported Functions from `kairos:policy/priority@0.3.0`
bool exports_kairos_policy_priority_rank(uint64_t now_us, exports_kairos_policy_priority_pending_columns_t *pending, exports_kairos_policy_priority_list_param_t *params, exports_kairos_policy_priority_ranking_t *ret, priority_policy_string_t *err);
void exports_kairos_policy_priority_task_finished(exports_kairos_policy_priority_finished_task_t *summary);

// Helper Functions

void kairos_policy_types_param_free(kairos_policy_types_param_t *ptr);

void kairos_policy_types_param_problem_free(kairos_policy_types_param_problem_t *ptr);

void exports_kairos_policy_priority_param_free(exports_kairos_policy_priority_param_t *ptr);

void priority_policy_list_u64_free(priority_policy_list_u64_t *ptr);

void priority_policy_list_u32_free(priority_policy_list_u32_t *ptr);

void priority_policy_list_f32_free(priority_policy_list_f32_t *ptr);

void exports_kairos_policy_priority_list_present_bits_free(exports_kairos_policy_priority_list_present_bits_t *ptr);

void exports_kairos_policy_priority_pending_columns_free(exports_kairos_policy_priority_pending_columns_t *ptr);

void exports_kairos_policy_priority_sort_keys_free(exports_kairos_policy_priority_sort_keys_t *ptr);

void exports_kairos_policy_priority_ranking_free(exports_kairos_policy_priority_ranking_t *ptr);

void exports_kairos_policy_priority_list_param_free(exports_kairos_policy_priority_list_param_t *ptr);

void exports_kairos_policy_priority_result_ranking_string_free(exports_kairos_policy_priority_result_ranking_string_t *ptr);

// Sets the string `ret` to reference the input string `s` without copying it
void priority_policy_string_set(priority_policy_string_t *ret, const char*s);

// Creates a copy of the input nul-terminated string `s` and
// stores it into the component model string `ret`.
void priority_policy_string_dup(priority_policy_string_t *ret, const char*s);

// Creates a copy of the input string `s` with length `len` and
// stores it into the component model string `ret`.
// The length is specified in code units (bytes for UTF-8, 16-bit values for UTF-16).
void priority_policy_string_dup_n(priority_policy_string_t *ret, const char*s, size_t len);

// Deallocates the string pointed to by `ret`, deallocating
// the memory behind the string.
void priority_policy_string_free(priority_policy_string_t *ret);

#ifdef __cplusplus
}
#endif
#endif
