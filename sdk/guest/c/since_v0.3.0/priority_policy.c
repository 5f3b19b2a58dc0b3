// The 0.2.0 bindings with the package version 0.3.0 (the priority interface did not change);
// regenerate with regen-bindings.sh once wit-bindgen-cli 0.60.0 is at hand.
#include "priority_policy.h"
#include <stdlib.h>
#include <string.h>

// Exported Functions from `kairos:policy/priority@0.3.0`

__attribute__((__weak__, __export_name__("cabi_post_kairos:policy/priority@0.3.0#rank")))
void __wasm_export_exports_kairos_policy_priority_rank_post_return(uint8_t * arg0) {
  switch ((int32_t) (int32_t) *((uint8_t*) (arg0 + 0))) {
    case 0: {
      switch ((int32_t) (int32_t) *((uint8_t*) (arg0 + sizeof(void*)))) {
        case 0: {
          size_t len = *((size_t*) (arg0 + (3*sizeof(void*))));
          if (len > 0) {
            uint8_t *ptr = *((uint8_t **) (arg0 + (2*sizeof(void*))));
            for (size_t i = 0; i < len; i++) {
              uint8_t *base = ptr + i * 8;
              (void) base;
            }
            free(ptr);
          }
          size_t len0 = *((size_t*) (arg0 + (5*sizeof(void*))));
          if (len0 > 0) {
            uint8_t *ptr1 = *((uint8_t **) (arg0 + (4*sizeof(void*))));
            for (size_t i2 = 0; i2 < len0; i2++) {
              uint8_t *base = ptr1 + i2 * 8;
              (void) base;
            }
            free(ptr1);
          }
          break;
        }
        case 1: {
          size_t len3 = *((size_t*) (arg0 + (3*sizeof(void*))));
          if (len3 > 0) {
            uint8_t *ptr4 = *((uint8_t **) (arg0 + (2*sizeof(void*))));
            for (size_t i5 = 0; i5 < len3; i5++) {
              uint8_t *base = ptr4 + i5 * 4;
              (void) base;
            }
            free(ptr4);
          }
          break;
        }
      }
      break;
    }
    case 1: {
      if ((*((size_t*) (arg0 + (2*sizeof(void*))))) > 0) {
        free(*((uint8_t **) (arg0 + sizeof(void*))));
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
  priority_policy_string_free(&ptr->name);
}

void kairos_policy_types_param_problem_free(kairos_policy_types_param_problem_t *ptr) {
  priority_policy_string_free(&ptr->name);
  priority_policy_string_free(&ptr->reason);
}

void exports_kairos_policy_priority_param_free(exports_kairos_policy_priority_param_t *ptr) {
  kairos_policy_types_param_free(ptr);
}

void priority_policy_list_u64_free(priority_policy_list_u64_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    uint64_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void priority_policy_list_u32_free(priority_policy_list_u32_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    uint32_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void priority_policy_list_f32_free(priority_policy_list_f32_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    float *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_priority_list_present_bits_free(exports_kairos_policy_priority_list_present_bits_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    exports_kairos_policy_priority_present_bits_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_priority_pending_columns_free(exports_kairos_policy_priority_pending_columns_t *ptr) {
  priority_policy_list_u64_free(&ptr->request);
  priority_policy_list_u64_free(&ptr->task);
  priority_policy_list_u64_free(&ptr->round_index);
  priority_policy_list_u64_free(&ptr->arrived_at_us);
  priority_policy_list_u64_free(&ptr->task_started_at_us);
  priority_policy_list_u32_free(&ptr->skipped);
  priority_policy_list_u64_free(&ptr->wait_ns);
  priority_policy_list_u64_free(&ptr->attained_service_ns);
  priority_policy_list_u64_free(&ptr->queued_ns);
  priority_policy_list_u64_free(&ptr->last_exec_ns);
  priority_policy_list_u64_free(&ptr->exec_ends_at_us);
  priority_policy_list_u64_free(&ptr->last_gen_ns);
  priority_policy_list_u32_free(&ptr->rounds_completed);
  priority_policy_list_u32_free(&ptr->remaining_rounds);
  priority_policy_list_f32_free(&ptr->remaining_seconds);
  exports_kairos_policy_priority_list_present_bits_free(&ptr->present);
}

void exports_kairos_policy_priority_sort_keys_free(exports_kairos_policy_priority_sort_keys_t *ptr) {
  priority_policy_list_u64_free(&ptr->major);
  priority_policy_list_u64_free(&ptr->minor);
}

void exports_kairos_policy_priority_ranking_free(exports_kairos_policy_priority_ranking_t *ptr) {
  switch ((int32_t) ptr->tag) {
    case 0: {
      exports_kairos_policy_priority_sort_keys_free(&ptr->val.keys);
      break;
    }
    case 1: {
      priority_policy_list_u32_free(&ptr->val.order);
      break;
    }
  }
}

void exports_kairos_policy_priority_list_param_free(exports_kairos_policy_priority_list_param_t *ptr) {
  size_t list_len = ptr->len;
  if (list_len > 0) {
    exports_kairos_policy_priority_param_t *list_ptr = ptr->ptr;
    for (size_t i = 0; i < list_len; i++) {
      exports_kairos_policy_priority_param_free(&list_ptr[i]);
    }
    free(list_ptr);
  }
}

void exports_kairos_policy_priority_result_ranking_string_free(exports_kairos_policy_priority_result_ranking_string_t *ptr) {
  if (!ptr->is_err) {
    exports_kairos_policy_priority_ranking_free(&ptr->val.ok);
  } else {
    priority_policy_string_free(&ptr->val.err);
  }
}

void priority_policy_string_set(priority_policy_string_t *ret, const char*s) {
  ret->ptr = (uint8_t*) s;
  ret->len = strlen(s);
}

void priority_policy_string_dup(priority_policy_string_t *ret, const char*s) {
  ret->len = strlen(s);
  ret->ptr = (uint8_t*) cabi_realloc(NULL, 0, 1, ret->len * 1);
  memcpy(ret->ptr, s, ret->len * 1);
}

void priority_policy_string_dup_n(priority_policy_string_t *ret, const char*s, size_t len) {
  ret->len = len;
  ret->ptr = (uint8_t*) cabi_realloc(NULL, 0, 1, ret->len * 1);
  memcpy(ret->ptr, s, ret->len * 1);
}

void priority_policy_string_free(priority_policy_string_t *ret) {
  if (ret->len > 0) {
    free(ret->ptr);
  }
  ret->ptr = NULL;
  ret->len = 0;
}

// Component Adapters

__attribute__((__export_name__("kairos:policy/priority@0.3.0#rank")))
uint8_t * __wasm_export_exports_kairos_policy_priority_rank(uint8_t * arg) {
  exports_kairos_policy_priority_pending_columns_t arg0 = (exports_kairos_policy_priority_pending_columns_t) {
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + 8))), (*((size_t*) (arg + (8+1*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+2*sizeof(void*))))), (*((size_t*) (arg + (8+3*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+4*sizeof(void*))))), (*((size_t*) (arg + (8+5*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+6*sizeof(void*))))), (*((size_t*) (arg + (8+7*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+8*sizeof(void*))))), (*((size_t*) (arg + (8+9*sizeof(void*))))) },
    (priority_policy_list_u32_t) (priority_policy_list_u32_t) { (uint32_t*)(*((uint8_t **) (arg + (8+10*sizeof(void*))))), (*((size_t*) (arg + (8+11*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+12*sizeof(void*))))), (*((size_t*) (arg + (8+13*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+14*sizeof(void*))))), (*((size_t*) (arg + (8+15*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+16*sizeof(void*))))), (*((size_t*) (arg + (8+17*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+18*sizeof(void*))))), (*((size_t*) (arg + (8+19*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+20*sizeof(void*))))), (*((size_t*) (arg + (8+21*sizeof(void*))))) },
    (priority_policy_list_u64_t) (priority_policy_list_u64_t) { (uint64_t*)(*((uint8_t **) (arg + (8+22*sizeof(void*))))), (*((size_t*) (arg + (8+23*sizeof(void*))))) },
    (priority_policy_list_u32_t) (priority_policy_list_u32_t) { (uint32_t*)(*((uint8_t **) (arg + (8+24*sizeof(void*))))), (*((size_t*) (arg + (8+25*sizeof(void*))))) },
    (priority_policy_list_u32_t) (priority_policy_list_u32_t) { (uint32_t*)(*((uint8_t **) (arg + (8+26*sizeof(void*))))), (*((size_t*) (arg + (8+27*sizeof(void*))))) },
    (priority_policy_list_f32_t) (priority_policy_list_f32_t) { (float*)(*((uint8_t **) (arg + (8+28*sizeof(void*))))), (*((size_t*) (arg + (8+29*sizeof(void*))))) },
    (exports_kairos_policy_priority_list_present_bits_t) (exports_kairos_policy_priority_list_present_bits_t) { (exports_kairos_policy_priority_present_bits_t*)(*((uint8_t **) (arg + (8+30*sizeof(void*))))), (*((size_t*) (arg + (8+31*sizeof(void*))))) },
  };
  exports_kairos_policy_priority_list_param_t arg1 = (exports_kairos_policy_priority_list_param_t) { (exports_kairos_policy_priority_param_t*)(*((uint8_t **) (arg + (8+32*sizeof(void*))))), (*((size_t*) (arg + (8+33*sizeof(void*))))) };
  exports_kairos_policy_priority_result_ranking_string_t ret;
  exports_kairos_policy_priority_ranking_t ok;
  priority_policy_string_t err;
  ret.is_err = !exports_kairos_policy_priority_rank((uint64_t) (*((int64_t*) (arg + 0))), &arg0, &arg1, &ok, &err);
  if (ret.is_err) {
    ret.val.err = err;
  }
  if (!ret.is_err) {
    ret.val.ok = ok;
  }
  free(arg);
  uint8_t *ptr = (uint8_t *) &RET_AREA;
  if ((ret).is_err) {
    const priority_policy_string_t *payload4 = &(ret).val.err;*((int8_t*)(ptr + 0)) = 1;
    *((size_t*)(ptr + (2*sizeof(void*)))) = (*payload4).len;
    *((uint8_t **)(ptr + sizeof(void*))) = (uint8_t *) (*payload4).ptr;
  } else {
    const exports_kairos_policy_priority_ranking_t *payload = &(ret).val.ok;*((int8_t*)(ptr + 0)) = 0;
    switch ((int32_t) (*payload).tag) {
      case 0: {
        const exports_kairos_policy_priority_sort_keys_t *payload2 = &(*payload).val.keys;
        *((int8_t*)(ptr + sizeof(void*))) = 0;
        *((size_t*)(ptr + (3*sizeof(void*)))) = ((*payload2).major).len;
        *((uint8_t **)(ptr + (2*sizeof(void*)))) = (uint8_t *) ((*payload2).major).ptr;
        *((size_t*)(ptr + (5*sizeof(void*)))) = ((*payload2).minor).len;
        *((uint8_t **)(ptr + (4*sizeof(void*)))) = (uint8_t *) ((*payload2).minor).ptr;
        break;
      }
      case 1: {
        const priority_policy_list_u32_t *payload3 = &(*payload).val.order;
        *((int8_t*)(ptr + sizeof(void*))) = 1;
        *((size_t*)(ptr + (3*sizeof(void*)))) = (*payload3).len;
        *((uint8_t **)(ptr + (2*sizeof(void*)))) = (uint8_t *) (*payload3).ptr;
        break;
      }
    }
  }
  return ptr;
}

__attribute__((__export_name__("kairos:policy/priority@0.3.0#task-finished")))
void __wasm_export_exports_kairos_policy_priority_task_finished(int64_t arg, int32_t arg0, int64_t arg1, int64_t arg2, int64_t arg3) {
  exports_kairos_policy_priority_finished_task_t arg4 = (exports_kairos_policy_priority_finished_task_t) {
    (uint64_t) (uint64_t) (arg),
    (uint32_t) (uint32_t) (arg0),
    (uint64_t) (uint64_t) (arg1),
    (uint64_t) (uint64_t) (arg2),
    (uint64_t) (uint64_t) (arg3),
  };
  exports_kairos_policy_priority_task_finished(&arg4);
}

// Ensure that the *_component_type.o object is linked in

extern void __component_type_object_force_link_priority_policy(void);
__attribute__((used))
void __component_type_object_force_link_priority_policy_public_use_in_this_compilation_unit(void) {
  __component_type_object_force_link_priority_policy();
}
