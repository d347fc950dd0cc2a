// The C ABI of the c10d shim (see c10d_shim.cpp and trainer/src/distributed/ffi.rs). Functions
// returning `char*` return NULL on success or a malloc'd error message.
#pragma once
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <string>

#include <torch/csrc/distributed/c10d/Backend.hpp>
#include <torch/csrc/distributed/c10d/Store.hpp>
#include <torch/csrc/distributed/c10d/Work.hpp>

struct trainer_c10d_store {
  c10::intrusive_ptr<c10d::Store> store;
};

struct trainer_c10d_group {
  c10::intrusive_ptr<c10d::Backend> backend;
};

struct trainer_c10d_work {
  c10::intrusive_ptr<c10d::Work> work;
};

namespace trainer_c10d {

// A malloc'd copy of `message` (the caller frees it with trainer_c10d_free_string).
char* copy_message(const std::string& message);

// Runs `body`, turning any exception into a returned message (NULL when none).
template <typename F>
char* guarded(F&& body) {
  try {
    body();
    return nullptr;
  } catch (const c10::Error& e) {
    return copy_message(e.what_without_backtrace());
  } catch (const std::exception& e) {
    return copy_message(e.what());
  } catch (...) {
    return copy_message("unknown C++ exception");
  }
}

inline std::chrono::milliseconds ms(int64_t value) { return std::chrono::milliseconds(value); }

}  // namespace trainer_c10d

extern "C" {
void trainer_c10d_free_string(char* message);
void trainer_c10d_free_bytes(uint8_t* bytes);
char* trainer_c10d_store_new(const char* host, uint16_t port, int is_server, int64_t world_size,
                             int64_t timeout_ms, const char* prefix, trainer_c10d_store** out);
void trainer_c10d_store_free(trainer_c10d_store* store);
char* trainer_c10d_store_set(trainer_c10d_store* store, const char* key, const uint8_t* value,
                             size_t len);
char* trainer_c10d_store_get(trainer_c10d_store* store, const char* key, int64_t timeout_ms,
                             uint8_t** value, size_t* len);
char* trainer_c10d_store_check(trainer_c10d_store* store, const char* key, int* present);
char* trainer_c10d_gloo_new(trainer_c10d_store* store, int rank, int size, int64_t timeout_ms,
                            trainer_c10d_group** out);
char* trainer_c10d_nccl_new(trainer_c10d_store* store, int rank, int size, int64_t timeout_ms,
                            trainer_c10d_group** out);
int trainer_c10d_has_nccl();
int trainer_c10d_cuda_mem_get_info(int device, uint64_t* free_bytes, uint64_t* total_bytes);
// Peak bytes allocated and reserved by libtorch's CUDA caching allocator on `device` since the
// process started or the last reset (`reset` != 0 resets after reading); -1 without CUDA.
int trainer_c10d_cuda_memory_peaks(int device, uint64_t* allocated, uint64_t* reserved, int reset);
void trainer_c10d_group_free(trainer_c10d_group* group);
char* trainer_c10d_allreduce_sum(trainer_c10d_group* group, at::Tensor* tensor, int64_t timeout_ms,
                                 trainer_c10d_work** work);
char* trainer_c10d_broadcast(trainer_c10d_group* group, at::Tensor* tensor, int root,
                             int64_t timeout_ms);
char* trainer_c10d_reduce_scatter_sum(trainer_c10d_group* group, at::Tensor* output,
                                      at::Tensor* input, int64_t timeout_ms,
                                      trainer_c10d_work** work);
char* trainer_c10d_all_gather(trainer_c10d_group* group, at::Tensor* output, at::Tensor* input,
                              int64_t timeout_ms, trainer_c10d_work** work);
char* trainer_c10d_barrier(trainer_c10d_group* group, int64_t timeout_ms);
char* trainer_c10d_work_wait(trainer_c10d_work* work, int64_t timeout_ms);
char* trainer_c10d_work_synchronize(trainer_c10d_work* work);
char* trainer_c10d_set_grad(at::Tensor* param, at::Tensor* grad);
void trainer_c10d_work_free(trainer_c10d_work* work);
}
