// The CUDA half of the c10d shim: ProcessGroupNCCL and the device's free memory. Compiled with
// TRAINER_C10D_NCCL only where the libtorch tch links is a CUDA build (libtorch_cuda.so, whose
// symbols these are) and the nvidia-* wheels' headers are found; otherwise the same entry points
// report that this build has no NCCL.
#include <cstdint>

#include "c10d_shim.h"

#ifdef TRAINER_C10D_NCCL
#include <c10/cuda/CUDACachingAllocator.h>
#include <torch/csrc/distributed/c10d/ProcessGroupNCCL.hpp>

// The CUDA runtime is loaded with libtorch_cuda; the two calls below bind to it at run time
// (weak, so linking needs no particular libcudart version).
#pragma weak cudaSetDevice
#pragma weak cudaMemGetInfo

extern "C" {

int trainer_c10d_has_nccl() { return 1; }

char* trainer_c10d_nccl_new(trainer_c10d_store* store, int rank, int size, int64_t timeout_ms,
                            trainer_c10d_group** out) {
  return trainer_c10d::guarded([&] {
    auto options = c10d::ProcessGroupNCCL::Options::create();
    options->timeout = trainer_c10d::ms(timeout_ms);
    auto group = c10::make_intrusive<c10d::ProcessGroupNCCL>(store->store, rank, size, options);
    *out = new trainer_c10d_group{group};
  });
}

int trainer_c10d_cuda_mem_get_info(int device, uint64_t* free_bytes, uint64_t* total_bytes) {
  if (&cudaSetDevice == nullptr || &cudaMemGetInfo == nullptr || cudaSetDevice(device) != cudaSuccess) {
    return -1;
  }
  size_t free_now = 0;
  size_t total = 0;
  if (cudaMemGetInfo(&free_now, &total) != cudaSuccess) {
    return -1;
  }
  *free_bytes = free_now;
  *total_bytes = total;
  return 0;
}

int trainer_c10d_cuda_memory_peaks(int device, uint64_t* allocated, uint64_t* reserved, int reset) {
  try {
    namespace allocator = c10::cuda::CUDACachingAllocator;
    const auto stats = allocator::getDeviceStats(static_cast<c10::DeviceIndex>(device));
    const auto aggregate = static_cast<size_t>(c10::CachingAllocator::StatType::AGGREGATE);
    *allocated = static_cast<uint64_t>(stats.allocated_bytes[aggregate].peak);
    *reserved = static_cast<uint64_t>(stats.reserved_bytes[aggregate].peak);
    if (reset != 0) {
      allocator::resetPeakStats(static_cast<c10::DeviceIndex>(device));
    }
    return 0;
  } catch (...) {
    return -1;
  }
}

}  // extern "C"

#else

extern "C" {

int trainer_c10d_has_nccl() { return 0; }

char* trainer_c10d_nccl_new(trainer_c10d_store*, int, int, int64_t, trainer_c10d_group**) {
  return trainer_c10d::copy_message(
      "this trainer was built without NCCL (its libtorch has no libtorch_cuda.so, or the nvidia "
      "wheels' nccl.h was not found at build time)");
}

int trainer_c10d_cuda_mem_get_info(int, uint64_t*, uint64_t*) { return -1; }

int trainer_c10d_cuda_memory_peaks(int, uint64_t*, uint64_t*, int) { return -1; }

}  // extern "C"

#endif
