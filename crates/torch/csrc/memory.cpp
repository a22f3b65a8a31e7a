// Pinned host memory without the deprecated device argument. tch 0.24 binds only
// `pin_memory(device)`, and libtorch 2.11 prints a warning each time a device is passed (TORCH_WARN,
// not once): every upload of a CUDA run (`pdt_torch::device::upload`) printed two lines, megabytes
// of stderr in a long run. `Tensor::pin_memory()` with no device pins for the current accelerator.

#include <ATen/core/Tensor.h>

#include "guard.h"

// `*out` receives a new tensor (owned by the caller, as tch's own functions return theirs): `self`
// in page-locked host memory.
extern "C" int pdt_pin_memory(const at::Tensor* self, at::Tensor** out, char* err,
                              size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    *out = new at::Tensor(self->pin_memory());
    return 0;
  });
}
