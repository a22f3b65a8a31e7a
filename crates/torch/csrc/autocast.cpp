// libtorch's autocast, which tch 0.24 does not bind: what `torch.autocast(device_type,
// dtype=torch.bfloat16)` does on entry and exit, for `pdt_torch::autocast` (a run's
// `run.matmul = "bf16"`). The same calls in the same order as PyTorch 2.11's
// `torch.amp.autocast_mode.autocast.__enter__` / `__exit__`, so the ops a forward pass dispatches
// inside are cast exactly as PyTorch casts them: the state is libtorch's own (thread-local dispatch
// keys and the cast cache), not a copy of its op lists.

#include <ATen/autocast_mode.h>

#include "guard.h"

namespace {
c10::DeviceType device_type(int cuda) { return cuda != 0 ? c10::DeviceType::CUDA : c10::DeviceType::CPU; }
}  // namespace

// Turns autocast on for the CPU (`cuda` = 0) or CUDA (1) in bfloat16 on this thread; `prev` receives
// what `pdt_autocast_exit` puts back: [enabled, dtype, cache enabled].
extern "C" int pdt_autocast_enter(int cuda, int* prev, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    const auto dev = device_type(cuda);
    prev[0] = at::autocast::is_autocast_enabled(dev) ? 1 : 0;
    prev[1] = static_cast<int>(at::autocast::get_autocast_dtype(dev));
    prev[2] = at::autocast::is_autocast_cache_enabled() ? 1 : 0;
    at::autocast::set_autocast_enabled(dev, true);
    at::autocast::set_autocast_dtype(dev, at::kBFloat16);
    at::autocast::increment_nesting();
    // torch.autocast's default cache_enabled=True: a weight is cast once per forward pass, not
    // once per use.
    at::autocast::set_autocast_cache_enabled(true);
    return 0;
  });
}

// Leaves the autocast region `pdt_autocast_enter` opened: the outermost exit drops the cast cache
// (as PyTorch does, so the next step casts the updated weights), then the previous state returns.
extern "C" int pdt_autocast_exit(int cuda, const int* prev, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    const auto dev = device_type(cuda);
    if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
    at::autocast::set_autocast_enabled(dev, prev[0] != 0);
    at::autocast::set_autocast_dtype(dev, static_cast<at::ScalarType>(prev[1]));
    at::autocast::set_autocast_cache_enabled(prev[2] != 0);
    return 0;
  });
}

// 1 if autocast is on for the device on this thread (tests), 0 if not.
extern "C" int pdt_autocast_enabled(int cuda, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] { return at::autocast::is_autocast_enabled(device_type(cuda)) ? 1 : 0; });
}
