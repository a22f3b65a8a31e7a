// The one libtorch setting promptdt needs that tch 0.24 does not bind: whether cuBLAS may compute
// float32 matrix products in TF32 (PyTorch's `torch.backends.cuda.matmul.allow_tf32`). Called only
// through `pdt_torch::device` (see its `Matmul` docs for why and when).

#include <ATen/Context.h>

#include "guard.h"

// The legacy setter keeps libtorch's two records of the setting (`float32_matmul_precision` and
// the per-backend `fp32_precision` of CUDA matmuls) in agreement; setting only the new one makes
// libtorch's own `allowTF32CuBLAS()` refuse the mix. It touches CUDA matmuls only: the CPU's
// (oneDNN) precision stays as it was.
extern "C" int pdt_set_cublas_tf32(int on, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    at::globalContext().setAllowTF32CuBLAS(on != 0);
    return 0;
  });
}

// 1 if cuBLAS may use TF32 now, 0 if not.
extern "C" int pdt_cublas_tf32(char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [] { return at::globalContext().allowTF32CuBLAS() ? 1 : 0; });
}
