// Written by hand after `wit-bindgen` 0.60.0 (c): see horizon_policy.h.
#include "horizon_policy.h"
#include <stdlib.h>
#include <string.h>

// Exported Functions from `kairos:policy/horizon@0.3.0`

__attribute__((__weak__, __export_name__("cabi_post_kairos:policy/horizon@0.3.0#choose")))
void __wasm_export_exports_kairos_policy_horizon_choose_post_return(uint8_t * arg0) {
  switch ((int32_t) (int32_t) *((uint8_t*) (arg0 + 0))) {
    case 0: {
      break;
    }
    case 1: {
      switch ((int32_t) (int32_t) *((uint8_t*) (arg0 + sizeof(void*)))) {
        case 0: {
          if ((*((size_t*) (arg0 + (3*sizeof(void*))))) > 0) {
            free(*((uint8_t **) (arg0 + (2*sizeof(void*)))));
          }
          if ((*((size_t*) (arg0 + (5*sizeof(void*))))) > 0) {
            free(*((uint8_t **) (arg0 + (4*sizeof(void*)))));
          }
          break;
        }
        case 1: {
          if ((*((size_t*) (arg0 + (3*sizeof(void*))))) > 0) {
            free(*((uint8_t **) (arg0 + (2*sizeof(void*)))));
          }
          break;
        }
        case 2: {
          if ((*((size_t*) (arg0 + (3*sizeof(void*))))) > 0) {
            free(*((uint8_t **) (arg0 + (2*sizeof(void*)))));
          }
          break;
        }
      }
      break;
    }
  }
}

// Canonical ABI intrinsics

__attribute__((__weak__, __export_name__("cabi_realloc")))
void *cabi_realloc(void *ptr, size_t old_size, size_t align, size_t new_size) {
  (void) old_size;
  if (new_size == 0) return (void*) align;
  void *ret = realloc(ptr, new_size);
  if (!ret) abort();
  return ret;
}

__attribute__((__aligned__(sizeof(void*))))
static uint8_t RET_AREA[(6*sizeof(void*))];

// Helper Functions

void kairos_policy_types_param_free(kairos_policy_types_param_t *ptr) {
  horizon_policy_string_free(&ptr->name);
}

void kairos_policy_types_param_problem_free(kairos_policy_types_param_problem_t *ptr) {
  horizon_policy_string_free(&ptr->name);
  horizon_policy_string_free(&ptr->reason);
}

void exports_kairos_policy_horizon_param_free(exports_kairos_policy_horizon_param_t *ptr) {
  kairos_policy_types_param_free(ptr);
}

void exports_kairos_policy_horizon_param_problem_free(exports_kairos_policy_horizon_param_problem_t *ptr) {
  kairos_policy_types_param_problem_free(ptr);
}

void horizon_policy_list_f32_free(horizon_policy_list_f32_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    float *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_horizon_chunk_free(exports_kairos_policy_horizon_chunk_t *ptr) {
  horizon_policy_list_f32_free(&ptr->updates);
  horizon_policy_list_f32_free(&ptr->actions);
}

void horizon_policy_list_u32_free(horizon_policy_list_u32_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    uint32_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_horizon_horizon_context_free(exports_kairos_policy_horizon_horizon_context_t *ptr) {
  horizon_policy_list_u32_free(&ptr->recent_horizons);
}

void exports_kairos_policy_horizon_horizon_error_free(exports_kairos_policy_horizon_horizon_error_t *ptr) {
  switch ((int32_t) ptr->tag) {
    case 0: {
      exports_kairos_policy_horizon_param_problem_free(&ptr->val.invalid_param);
      break;
    }
    case 1: {
      horizon_policy_string_free(&ptr->val.unsupported);
      break;
    }
    case 2: {
      horizon_policy_string_free(&ptr->val.failed);
      break;
    }
  }
}

void exports_kairos_policy_horizon_list_param_free(exports_kairos_policy_horizon_list_param_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    exports_kairos_policy_horizon_param_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
      exports_kairos_policy_horizon_param_free(&list_ptr[i]);
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_horizon_result_u32_horizon_error_free(exports_kairos_policy_horizon_result_u32_horizon_error_t *ptr) {
  if (!ptr->is_err) {
  } else {
    exports_kairos_policy_horizon_horizon_error_free(&ptr->val.err);
  }
}

void horizon_policy_string_set(horizon_policy_string_t *ret, const char*s) {
  ret->ptr = (uint8_t*) s;
  ret->len = strlen(s);
}

void horizon_policy_string_dup(horizon_policy_string_t *ret, const char*s) {
  ret->len = strlen(s);
  ret->ptr = (uint8_t*) cabi_realloc(NULL, 0, 1, ret->len * 1);
  memcpy(ret->ptr, s, ret->len * 1);
}

void horizon_policy_string_dup_n(horizon_policy_string_t *ret, const char*s, size_t len) {
  ret->len = len;
  ret->ptr = (uint8_t*) cabi_realloc(NULL, 0, 1, ret->len * 1);
  memcpy(ret->ptr, s, ret->len * 1);
}

void horizon_policy_string_free(horizon_policy_string_t *ret) {
  if (ret->len > 0) {
    free(ret->ptr);
  }
  ret->ptr = NULL;
  ret->len = 0;
}

// Component Adapters

__attribute__((__export_name__("kairos:policy/horizon@0.3.0#choose")))
uint8_t * __wasm_export_exports_kairos_policy_horizon_choose(uint8_t * arg) {
  // With `load` the arguments flatten to more than 16 values, so the canonical ABI passes
  // them in memory: the tuple (chunk, context, params), 104 bytes, 8-aligned, allocated by the
  // host with cabi_realloc and owned by the callee.
  exports_kairos_policy_horizon_chunk_t arg15 = (exports_kairos_policy_horizon_chunk_t) {
    (uint32_t) (*((int32_t*) (arg + 0))),
    (uint32_t) (*((int32_t*) (arg + 4))),
    (uint32_t) (*((int32_t*) (arg + 8))),
    (uint32_t) (*((int32_t*) (arg + 12))),
    (horizon_policy_list_f32_t) { (float*)(*((uint8_t **) (arg + 16))), (*((size_t*) (arg + 20))) },
    (horizon_policy_list_f32_t) { (float*)(*((uint8_t **) (arg + 24))), (*((size_t*) (arg + 28))) },
  };
  exports_kairos_policy_horizon_option_server_load_t load;
  switch ((int32_t) (*((uint8_t*) (arg + 64)))) {
    case 0: {
      load.is_some = false;
      break;
    }
    case 1: {
      load.is_some = true;
      load.val = (exports_kairos_policy_horizon_server_load_t) {
        (uint32_t) (*((int32_t*) (arg + 72))),
        (uint32_t) (*((int32_t*) (arg + 76))),
        (uint32_t) (*((int32_t*) (arg + 80))),
        (uint64_t) (*((int64_t*) (arg + 88))),
      };
      break;
    }
    default: {
      __builtin_trap();
    }
  }
  exports_kairos_policy_horizon_horizon_context_t arg16 = (exports_kairos_policy_horizon_horizon_context_t) {
    (uint32_t) (*((int32_t*) (arg + 32))),
    (uint32_t) (*((int32_t*) (arg + 36))),
    *((float*) (arg + 40)),
    (uint64_t) (*((int64_t*) (arg + 48))),
    (horizon_policy_list_u32_t) { (uint32_t*)(*((uint8_t **) (arg + 56))), (*((size_t*) (arg + 60))) },
    load,
  };
  exports_kairos_policy_horizon_list_param_t arg17 = (exports_kairos_policy_horizon_list_param_t) { (exports_kairos_policy_horizon_param_t*)(*((uint8_t **) (arg + 96))), (*((size_t*) (arg + 100))) };
  free(arg);
  exports_kairos_policy_horizon_result_u32_horizon_error_t ret;
  uint32_t ok;
  exports_kairos_policy_horizon_horizon_error_t err;
  ret.is_err = !exports_kairos_policy_horizon_choose(&arg15, &arg16, &arg17, &ok, &err);
  if (ret.is_err) {
    ret.val.err = err;
  }
  if (!ret.is_err) {
    ret.val.ok = ok;
  }
  uint8_t *ptr = (uint8_t *) &RET_AREA;
  if ((ret).is_err) {
    const exports_kairos_policy_horizon_horizon_error_t *payload18 = &(ret).val.err;*((int8_t*)(ptr + 0)) = 1;
    switch ((int32_t) (*payload18).tag) {
      case 0: {
        const exports_kairos_policy_horizon_param_problem_t *payload19 = &(*payload18).val.invalid_param;
        *((int8_t*)(ptr + sizeof(void*))) = 0;
        *((size_t*)(ptr + (3*sizeof(void*)))) = ((*payload19).name).len;
        *((uint8_t **)(ptr + (2*sizeof(void*)))) = (uint8_t *) ((*payload19).name).ptr;
        *((size_t*)(ptr + (5*sizeof(void*)))) = ((*payload19).reason).len;
        *((uint8_t **)(ptr + (4*sizeof(void*)))) = (uint8_t *) ((*payload19).reason).ptr;
        break;
      }
      case 1: {
        const horizon_policy_string_t *payload20 = &(*payload18).val.unsupported;
        *((int8_t*)(ptr + sizeof(void*))) = 1;
        *((size_t*)(ptr + (3*sizeof(void*)))) = (*payload20).len;
        *((uint8_t **)(ptr + (2*sizeof(void*)))) = (uint8_t *) (*payload20).ptr;
        break;
      }
      case 2: {
        const horizon_policy_string_t *payload21 = &(*payload18).val.failed;
        *((int8_t*)(ptr + sizeof(void*))) = 2;
        *((size_t*)(ptr + (3*sizeof(void*)))) = (*payload21).len;
        *((uint8_t **)(ptr + (2*sizeof(void*)))) = (uint8_t *) (*payload21).ptr;
        break;
      }
    }
  } else {
    const uint32_t *payload = &(ret).val.ok;*((int8_t*)(ptr + 0)) = 0;
    *((int32_t*)(ptr + sizeof(void*))) = (int32_t) (*payload);
  }
  return ptr;
}

// Ensure that the *_component_type.o object is linked in

extern void __component_type_object_force_link_horizon_policy(void);
__attribute__((used))
void __component_type_object_force_link_horizon_policy_public_use_in_this_compilation_unit(void) {
  __component_type_object_force_link_horizon_policy();
}
