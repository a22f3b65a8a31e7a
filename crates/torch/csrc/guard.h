// What every function of csrc/ shares: none may let a C++ exception unwind into Rust. `guarded`
// runs `f` (which returns 0 or a non-negative answer) and turns any exception into -1 with its
// message copied into `err` (NUL-terminated, cut to `err_len`), which `pdt_torch::ffi` reads.
#pragma once

#include <cstring>
#include <exception>

namespace pdt {

inline void copy_message(const char* what, char* err, size_t err_len) noexcept {
  if (err == nullptr || err_len == 0) return;
  std::strncpy(err, what, err_len - 1);
  err[err_len - 1] = '\0';
}

template <class F>
int guarded(char* err, size_t err_len, F&& f) noexcept {
  try {
    return f();
  } catch (const std::exception& e) {
    copy_message(e.what(), err, err_len);
  } catch (...) {
    copy_message("unknown C++ exception", err, err_len);
  }
  return -1;
}

}  // namespace pdt
