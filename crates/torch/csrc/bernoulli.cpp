// at::dropout's Bernoulli noise on the CPU: the bits libtorch draws, drawn faster.
//
// On a CPU that is not Intel's (or a libtorch without MKL), `bernoulli_(p)` on the CPU is
// `templates::cpu::bernoulli_kernel`: one element after another through TensorIterator, each an
// out-of-line `CPUGeneratorImpl::random64()` (two outputs of the generator's MT19937, the first
// the high word), `x = (v & (2^53 - 1)) * 2^-53` and `x < p`. That loop was a tenth of a training
// step (`train_b64`, one thread, AMD EPYC: 5.4 million draws, 31 ms of about 305). Here the same
// sequence is drawn from a copy of the generator's MT19937 state a block at a time in loops the
// compiler vectorises (6 ms), and the state put back where libtorch's loop leaves it: the same
// mask, the same generator afterwards.
//
// Where libtorch draws otherwise (an Intel CPU with MKL draws through MKL's VSL stream, seeded from
// the generator), the bits would differ: a probe compares both ways once per process, and
// `pdt_bernoulli_cpu` answers 0 (not drawn) unless they agree, so the caller uses `bernoulli_`.

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/core/MT19937RNGEngine.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <mutex>

#include "guard.h"

namespace {

constexpr int kN = 624;  // at::MERSENNE_STATE_N
constexpr int kM = 397;  // at::MERSENNE_STATE_M
constexpr uint32_t kMatrixA = 0x9908b0df;
constexpr uint32_t kUpper = 0x80000000;
constexpr uint32_t kLower = 0x7fffffff;

// Branch-free, so the loops vectorise.
inline uint32_t twist(uint32_t u, uint32_t v) {
  return (((u & kUpper) | (v & kLower)) >> 1) ^ ((0u - (v & 1u)) & kMatrixA);
}

// at::mt19937's `next_state`: the same three loops.
void next_state(uint32_t* s) {
  for (int k = 0; k < kN - kM; ++k) s[k] = s[k + kM] ^ twist(s[k], s[k + 1]);
  for (int k = kN - kM; k < kN - 1; ++k) s[k] = s[k + kM - kN] ^ twist(s[k], s[k + 1]);
  s[kN - 1] = s[kM - 1] ^ twist(s[kN - 1], s[0]);
}

inline uint32_t temper(uint32_t y) {
  y ^= (y >> 11);
  y ^= (y << 7) & 0x9d2c5680;
  y ^= (y << 15) & 0xefc60000;
  y ^= (y >> 18);
  return y;
}

// at::mt19937's `operator()` on a copy of its state.
inline uint32_t next(at::mt19937_data_pod& d) {
  if (--d.left_ == 0) {
    next_state(d.state_.data());
    d.left_ = kN;
    d.next_ = 0;
  }
  return temper(d.state_[d.next_++]);
}

// One element of `bernoulli_kernel`: `x = (v & (2^53 - 1)) * 2^-53 < p` with v = hi << 32 | lo.
// x is exact (an integer m < 2^53 times a power of two), so x < p is m < p * 2^53 (also exact),
// that is m < ceil(p * 2^53) = t, compared as two 32-bit words (which SSE2 vectorises; 64-bit
// compares it does not).
struct Threshold {
  uint32_t hi;
  uint32_t lo;

  explicit Threshold(double p) {
    const auto t = static_cast<uint64_t>(std::ceil(p * static_cast<double>(uint64_t{1} << 53)));
    hi = static_cast<uint32_t>(t >> 32);
    lo = static_cast<uint32_t>(t);
  }
};

inline float draw_one(uint32_t hi, uint32_t lo, Threshold t) {
  hi &= 0x1fffffu;  // the 21 high bits of the 53
  return static_cast<float>(static_cast<int>(hi < t.hi) | (static_cast<int>(hi == t.hi) & static_cast<int>(lo < t.lo)));
}

// `out[0..n)` as `bernoulli_kernel` fills a contiguous float tensor from the MT19937 state `d`,
// `d` left as libtorch's loop leaves it. Whole blocks of the state at a time: `d.left_ - 1` outputs
// are left in a block (at `d.next_`), and a block just twisted is taken as `left_ = 625`, `next_ =
// 0` (libtorch's `operator()` twists when `left_` falls to 0, then reads output 0 and leaves 624).
void fill(at::mt19937_data_pod& d, float* out, int64_t n, double p) {
  const Threshold t(p);
  int64_t i = 0;
  while (i < n) {
    int left = d.left_ - 1;
    if (left == 0) {
      next_state(d.state_.data());
      d.left_ = kN + 1;
      d.next_ = 0;
      left = kN;
    }
    const int64_t pairs = std::min<int64_t>(left / 2, n - i);
    if (pairs == 0) {
      // One output left in the block: the element's high word from it, its low word from the next.
      const uint32_t hi = next(d);
      const uint32_t lo = next(d);
      out[i++] = draw_one(hi, lo, t);
      continue;
    }
    const uint32_t* src = d.state_.data() + d.next_;
    float* dst = out + i;
    for (int64_t k = 0; k < pairs; ++k) dst[k] = draw_one(temper(src[2 * k]), temper(src[2 * k + 1]), t);
    d.next_ += static_cast<uint32_t>(2 * pairs);
    d.left_ -= static_cast<int>(2 * pairs);
    i += pairs;
  }
}

bool usable(const at::Tensor& t) {
  return t.defined() && t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous();
}

bool same_engine(at::CPUGeneratorImpl* a, at::CPUGeneratorImpl* b) {
  const auto x = a->engine().data();
  const auto y = b->engine().data();
  return x.left_ == y.left_ && x.next_ == y.next_ && x.state_ == y.state_;
}

// Draws `t` from `gen` (locked by the caller); false if the state is not a valid MT19937 one.
bool draw(at::CPUGeneratorImpl* gen, at::Tensor& t, double p) {
  at::mt19937 engine = gen->engine();
  if (!engine.is_valid()) return false;
  at::mt19937_data_pod d = engine.data();
  fill(d, t.data_ptr<float>(), t.numel(), p);
  engine.set_data(d);
  gen->set_engine(engine);
  return true;
}

// Whether `fill` draws what libtorch's `bernoulli_` draws here: the same bits, and each generator
// left in the same state, for sizes across several MT19937 blocks and from the middle of one.
bool agrees_with_libtorch() {
  for (const int64_t n : {int64_t{1}, int64_t{311}, int64_t{5000}}) {
    at::Generator mine = at::make_generator<at::CPUGeneratorImpl>(20261128);
    at::Generator theirs = at::make_generator<at::CPUGeneratorImpl>(20261128);
    auto* m = at::check_generator<at::CPUGeneratorImpl>(mine);
    auto* t = at::check_generator<at::CPUGeneratorImpl>(theirs);
    m->random();  // start mid-block, as a run's generator does
    t->random();
    at::Tensor a = at::empty({n}, at::TensorOptions().dtype(at::kFloat));
    at::Tensor b = at::empty({n}, at::TensorOptions().dtype(at::kFloat));
    a.bernoulli_(0.9, theirs);
    {
      std::lock_guard<std::mutex> lock(m->mutex_);
      if (!draw(m, b, 0.9)) return false;
    }
    if (!a.equal(b) || !same_engine(m, t)) return false;
  }
  return true;
}

}  // namespace

// Fills `*self` (contiguous float, on the CPU) with `bernoulli_(p)`'s bits from the default CPU
// generator and answers 1; answers 0 without drawing where that is not what libtorch would draw
// (the caller then calls `bernoulli_`).
extern "C" int pdt_bernoulli_cpu(at::Tensor* self, double p, char* err, size_t err_len) noexcept {
  return pdt::guarded(err, err_len, [&] {
    static const bool agrees = agrees_with_libtorch();
    if (!agrees || !usable(*self) || !(p >= 0.0 && p <= 1.0)) return 0;
    auto* gen = at::check_generator<at::CPUGeneratorImpl>(at::detail::getDefaultCPUGenerator());
    std::lock_guard<std::mutex> lock(gen->mutex_);
    return draw(gen, *self, p) ? 1 : 0;
  });
}
