// The state of libtorch's default random generators, taken and put back. tch 0.24 binds only
// `manual_seed`. A run of a pack that fine-tunes before each test task (MT-BC-Finetune) draws its
// dropout from the process's generator; with its state kept between its turns, the run need not
// hold the generator while its episodes run, and the pack's other runs step and evaluate meanwhile
// (`pdt_model::device::GeneratorState`).

#include <ATen/Context.h>
#include <ATen/core/Generator.h>
#include <ATen/core/Tensor.h>

#include <mutex>

#include "guard.h"

namespace {

// The default generator of the CPU (`cuda_index` < 0) or of CUDA device `cuda_index`.
at::Generator generator(int cuda_index) {
  if (cuda_index < 0) return at::globalContext().defaultGenerator(at::Device(at::kCPU));
  return at::globalContext().defaultGenerator(
      at::Device(at::kCUDA, static_cast<c10::DeviceIndex>(cuda_index)));
}

}  // namespace

// `*out` receives a new tensor (owned by the caller): the generator's state.
extern "C" int pdt_generator_state(int cuda_index, at::Tensor** out, char* err,
                                   size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    at::Generator gen = generator(cuda_index);
    std::lock_guard<std::mutex> lock(gen.mutex());
    *out = new at::Tensor(gen.get_state());
    return 0;
  });
}

// Sets the generator's state to `state` (one taken by `pdt_generator_state` of the same generator).
extern "C" int pdt_set_generator_state(int cuda_index, const at::Tensor* state, char* err,
                                       size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    at::Generator gen = generator(cuda_index);
    std::lock_guard<std::mutex> lock(gen.mutex());
    gen.set_state(*state);
    return 0;
  });
}
