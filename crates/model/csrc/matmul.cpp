// The one libtorch setting promptdt needs that tch 0.24 does not bind: whether cuBLAS may compute
// float32 matrix products in TF32 (PyTorch's `torch.backends.cuda.matmul.allow_tf32`). Compiled by
// crates/model/build.rs against the headers of the libtorch the workspace links (2.11.0), and
// called only through `pdt_model::device` (see its `Matmul` docs for why and when).
//
// Both calls catch every C++ exception: one must never unwind into Rust. They return 0 on success
// (the query: 0 or 1) and -1 if libtorch threw, with its message copied into `err` (NUL-terminated,
// cut to `err_len`).

#include <ATen/Context.h>

#include <cstring>
#include <exception>

namespace {
void copy_message(const char* what, char* err, size_t err_len) {
  if (err == nullptr || err_len == 0) return;
  std::strncpy(err, what, err_len - 1);
  err[err_len - 1] = '\0';
}
}  // namespace

// The legacy setter keeps libtorch's two records of the setting (`float32_matmul_precision` and
// the per-backend `fp32_precision` of CUDA matmuls) in agreement; setting only the new one makes
// libtorch's own `allowTF32CuBLAS()` refuse the mix. It touches CUDA matmuls only: the CPU's
// (oneDNN) precision stays as it was.
extern "C" int pdt_set_cublas_tf32(int on, char* err, size_t err_len) noexcept {
  try {
    at::globalContext().setAllowTF32CuBLAS(on != 0);
    return 0;
  } catch (const std::exception& e) {
    copy_message(e.what(), err, err_len);
  } catch (...) {
    copy_message("unknown C++ exception", err, err_len);
  }
  return -1;
}

extern "C" int pdt_cublas_tf32(char* err, size_t err_len) noexcept {
  try {
    return at::globalContext().allowTF32CuBLAS() ? 1 : 0;
  } catch (const std::exception& e) {
    copy_message(e.what(), err, err_len);
  } catch (...) {
    copy_message("unknown C++ exception", err, err_len);
  }
  return -1;
}
