// libtorch's own profiler (Kineto), which tch 0.24 does not bind: `promptdt bench --profile` counts
// the operators a step runs and, on CUDA, the kernels it launches (and where their time goes).
// Compiled by crates/torch/build.rs; called only through `pdt_torch::profiler`.
//
// 0 is success, -1 a failure with libtorch's message in `err` (guard.h).

#include <ActivityType.h>
#include <torch/csrc/autograd/profiler_kineto.h>

#include <cstdint>
#include <set>

#include "guard.h"

namespace {
using torch::profiler::impl::ActivityType;
using torch::profiler::impl::ProfilerConfig;
using torch::profiler::impl::ProfilerState;

// What an event is, as `pdt_torch::profiler::EventKind` numbers it.
int kind_of(uint8_t activity) {
  switch (static_cast<libkineto::ActivityType>(activity)) {
    case libkineto::ActivityType::CPU_OP:
      return 0;
    case libkineto::ActivityType::CONCURRENT_KERNEL:
      return 1;
    case libkineto::ActivityType::GPU_MEMCPY:
      return 2;
    case libkineto::ActivityType::GPU_MEMSET:
      return 3;
    case libkineto::ActivityType::CUDA_RUNTIME:
    case libkineto::ActivityType::CUDA_DRIVER:
      return 4;
    default:
      return 5;
  }
}
}  // namespace

extern "C" int pdt_profiler_start(int with_cuda, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    const ProfilerConfig config(ProfilerState::KINETO);
    std::set<ActivityType> activities{ActivityType::CPU};
    if (with_cuda != 0) activities.insert(ActivityType::CUDA);
    torch::autograd::profiler::prepareProfiler(config, activities);
    torch::autograd::profiler::enableProfiler(config, activities);
    return 0;
  });
}

// Stops the profiler and hands each event to `sink` (name, kind, duration in ns). `sink` must not
// unwind (the Rust side catches its own panics).
extern "C" int pdt_profiler_stop(void* ctx,
                                 void (*sink)(void*, const char*, int, uint64_t),
                                 char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    auto result = torch::autograd::profiler::disableProfiler();
    if (result) {
      for (const auto& e : result->events()) {
        const std::string name = e.name();
        sink(ctx, name.c_str(), kind_of(e.activityType()), e.durationNs());
      }
    }
    return 0;
  });
}
