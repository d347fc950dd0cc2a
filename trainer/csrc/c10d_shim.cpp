// The C ABI between `trainer::distributed` (Rust) and PyTorch's c10d: a TCPStore (with an optional
// key prefix), a ProcessGroupGloo, and the collectives the trainer uses, on the `at::Tensor*`
// handles tch passes around, and one autograd setter tch lacks (a parameter's gradient tensor).
// Every entry point catches C++ exceptions and returns them as a malloc'd message (NULL on
// success) that Rust frees with `trainer_c10d_free_string`. The logic (which collective, when,
// what a failure means) lives in Rust; this file only translates calls.
#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>

#include "c10d_shim.h"

namespace trainer_c10d {

char* copy_message(const std::string& message) {
  char* out = static_cast<char*>(std::malloc(message.size() + 1));
  if (out != nullptr) {
    std::memcpy(out, message.c_str(), message.size() + 1);
  }
  return out;
}

}  // namespace trainer_c10d

namespace {

using trainer_c10d::guarded;
using trainer_c10d::ms;

// Waits for a collective; a wait that returns false (Gloo's timeout path) is an error too.
void finish(const c10::intrusive_ptr<c10d::Work>& work, int64_t timeout_ms) {
  if (!work->wait(ms(timeout_ms))) {
    throw std::runtime_error("timed out after " + std::to_string(timeout_ms) + " ms");
  }
}

}  // namespace

extern "C" {

void trainer_c10d_free_string(char* message) { std::free(message); }

char* trainer_c10d_store_new(const char* host, uint16_t port, int is_server, int64_t world_size,
                             int64_t timeout_ms, const char* prefix, trainer_c10d_store** out) {
  return guarded([&] {
    c10d::TCPStoreOptions options;
    options.port = port;
    options.isServer = is_server != 0;
    options.numWorkers = static_cast<std::size_t>(world_size);
    // Rank 0 hosts the store without waiting for the others: the process group's own rendezvous
    // (and its timeout) is where a missing rank shows up.
    options.waitWorkers = false;
    options.timeout = ms(timeout_ms);
    c10::intrusive_ptr<c10d::Store> store = c10::make_intrusive<c10d::TCPStore>(host, options);
    if (prefix != nullptr && prefix[0] != '\0') {
      store = c10::make_intrusive<c10d::PrefixStore>(prefix, store);
    }
    *out = new trainer_c10d_store{store};
  });
}

void trainer_c10d_store_free(trainer_c10d_store* store) { delete store; }

char* trainer_c10d_store_set(trainer_c10d_store* store, const char* key, const uint8_t* value,
                             size_t len) {
  return guarded([&] { store->store->set(key, std::vector<uint8_t>(value, value + len)); });
}

char* trainer_c10d_store_get(trainer_c10d_store* store, const char* key, int64_t timeout_ms,
                             uint8_t** value, size_t* len) {
  return guarded([&] {
    store->store->wait({key}, ms(timeout_ms));
    std::vector<uint8_t> bytes = store->store->get(key);
    *len = bytes.size();
    *value = static_cast<uint8_t*>(std::malloc(bytes.size() + 1));
    if (*value == nullptr) {
      throw std::bad_alloc();
    }
    std::memcpy(*value, bytes.data(), bytes.size());
  });
}

char* trainer_c10d_store_check(trainer_c10d_store* store, const char* key, int* present) {
  return guarded([&] { *present = store->store->check({key}) ? 1 : 0; });
}

void trainer_c10d_free_bytes(uint8_t* bytes) { std::free(bytes); }

char* trainer_c10d_gloo_new(trainer_c10d_store* store, int rank, int size, int64_t timeout_ms,
                            trainer_c10d_group** out) {
  return guarded([&] {
    auto options = c10d::ProcessGroupGloo::Options::create_default(ms(timeout_ms));
    auto group = c10::make_intrusive<c10d::ProcessGroupGloo>(store->store, rank, size, options);
    *out = new trainer_c10d_group{group};
  });
}

void trainer_c10d_group_free(trainer_c10d_group* group) { delete group; }

char* trainer_c10d_allreduce_sum(trainer_c10d_group* group, at::Tensor* tensor, int64_t timeout_ms,
                                 trainer_c10d_work** work) {
  return guarded([&] {
    std::vector<at::Tensor> tensors{*tensor};
    c10d::AllreduceOptions options;
    options.reduceOp = c10d::ReduceOp::SUM;
    options.timeout = ms(timeout_ms);
    auto pending = group->backend->allreduce(tensors, options);
    if (work != nullptr) {
      *work = new trainer_c10d_work{pending};
    } else {
      finish(pending, timeout_ms);
    }
  });
}

char* trainer_c10d_broadcast(trainer_c10d_group* group, at::Tensor* tensor, int root,
                             int64_t timeout_ms) {
  return guarded([&] {
    std::vector<at::Tensor> tensors{*tensor};
    c10d::BroadcastOptions options;
    options.rootRank = root;
    options.timeout = ms(timeout_ms);
    finish(group->backend->broadcast(tensors, options), timeout_ms);
  });
}

char* trainer_c10d_reduce_scatter_sum(trainer_c10d_group* group, at::Tensor* output,
                                      at::Tensor* input, int64_t timeout_ms,
                                      trainer_c10d_work** work) {
  return guarded([&] {
    c10d::ReduceScatterOptions options;
    options.reduceOp = c10d::ReduceOp::SUM;
    options.timeout = ms(timeout_ms);
    auto pending = group->backend->_reduce_scatter_base(*output, *input, options);
    if (work != nullptr) {
      *work = new trainer_c10d_work{pending};
    } else {
      finish(pending, timeout_ms);
    }
  });
}

char* trainer_c10d_all_gather(trainer_c10d_group* group, at::Tensor* output, at::Tensor* input,
                              int64_t timeout_ms, trainer_c10d_work** work) {
  return guarded([&] {
    c10d::AllgatherOptions options;
    options.timeout = ms(timeout_ms);
    auto pending = group->backend->_allgather_base(*output, *input, options);
    if (work != nullptr) {
      *work = new trainer_c10d_work{pending};
    } else {
      finish(pending, timeout_ms);
    }
  });
}

char* trainer_c10d_barrier(trainer_c10d_group* group, int64_t timeout_ms) {
  return guarded([&] {
    c10d::BarrierOptions options;
    options.timeout = ms(timeout_ms);
    finish(group->backend->barrier(options), timeout_ms);
  });
}

char* trainer_c10d_work_wait(trainer_c10d_work* work, int64_t timeout_ms) {
  return guarded([&] { finish(work->work, timeout_ms); });
}

// Orders the calling thread's current device stream after the collective without blocking the
// host (NCCL: the stream waits on the collective's end event); a no-op for CPU work.
char* trainer_c10d_work_synchronize(trainer_c10d_work* work) {
  return guarded([&] { work->work->synchronize(); });
}

void trainer_c10d_work_free(trainer_c10d_work* work) { delete work; }

// Makes `grad` (same shape, dtype and device as `param`) the gradient the autograd engine
// accumulates `param`'s into: with one already defined it adds in place, so a view into a flat
// buffer receives the backward's gradients where they are reduced. Not a collective, but the
// trainer's only other reach past tch's API, so it lives here beside the c10d calls.
char* trainer_c10d_set_grad(at::Tensor* param, at::Tensor* grad) {
  return guarded([&] {
    TORCH_CHECK(param->sizes() == grad->sizes() && param->dtype() == grad->dtype() &&
                    param->device() == grad->device(),
                "a gradient must match its parameter's shape, dtype and device");
    param->mutable_grad() = *grad;
  });
}

}  // extern "C"
