// Fused CPU kernels (C++17, OpenMP) for the multi-resolution permutohedral hash encoding, a cubic
// (trilinear, 8-corner) hash grid written with the same care for comparison, and a random-access
// microbenchmark giving the machine's limit. The maths is in nerf/encoding.py; the pure-torch
// references there are what tests/nerf/test_encoding.py compares these kernels against.
//
// Inputs: x [N, 3] float32, table [R, F] float32 with offsets [L + 1] int64 (level l's rows are
// offsets[l] .. offsets[l + 1], a power of two of them: levels coarser than the table get fewer rows),
// coef [L, 3] (the per-level, per-axis factor: 1 / (sqrt((i+1)(i+2)) sigma_l) for the lattice,
// 1 / sigma_l for the cubic grid), shifts [L, 3]. Output [N, L * F], level-major within a row.
//
// What makes it fast (DESIGN section 8, measured on 2-core Zen 1 and Sapphire Rapids VMs):
// - Work is split by LEVEL (one OpenMP task per level, finest first): a level's table stays in
//   cache while all points pass, and its gradient slice has a single writer, so no atomics, no
//   per-thread copies of the table gradient and no reduction pass; the slice is zeroed by that
//   writer just before use. Results do not depend on the thread count.
// - Points go through in blocks: the simplices of block k+1 are computed (vectorised) and their
//   table rows prefetched before block k is gathered, so many random reads are in flight.
// - When x requires grad, either the forward also writes d features / d x (a [3, F] Jacobian per
//   point and level, from the rows it has just read) and the backward contracts it with grad_out in
//   a streaming pass, or the backward reads the rows again next to its table-gradient scatter;
//   which is faster depends on the machine (JACOBIAN_IN_FORWARD in nerf/encoding.py).
// - Features are produced into / consumed from a level-major [L, N, F] scratch, transposed once,
//   instead of striding through the [N, L * F] rows once per level.
// - No page faults in steady state: outputs come from a small pool of blocks, scratch is kept.
// - Power-of-two masks, constants hoisted per level, no libm calls, the feature count a
//   compile-time constant for F in {1, 2, 4, 8}; AVX2 and AVX-512 builds of the same code picked at
//   run time.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <new>
#include <optional>
#include <unordered_map>
#include <vector>

// The per-level kernels, compiled for baseline x86-64 and, on x86, once more for AVX2 (8-wide) and
// once for AVX-512 (16-wide, 32 vector registers: the lattice arithmetic of a block without
// spills); no FMA, so all three give bit-identical results. The CPU is asked at run time.
namespace base {
#include "permuto_cpu_kernels.h"
}  // namespace base
#if defined(__x86_64__) && defined(__GNUC__)
#pragma GCC push_options
#pragma GCC target("avx2")
namespace avx2 {
#include "permuto_cpu_kernels.h"
}  // namespace avx2
#pragma GCC pop_options
#pragma GCC push_options
#pragma GCC target("avx2,avx512f,avx512vl,avx512bw,avx512dq,prefer-vector-width=512")
namespace avx512 {
#include "permuto_cpu_kernels.h"
}  // namespace avx512
#pragma GCC pop_options
#define PAG_HAVE_X86_VARIANTS 1
#endif

namespace {

using base::BLOCK;

enum class Isa { base, avx2, avx512 };

// The widest build this CPU runs; PAG_NO_AVX512=1 / PAG_NO_AVX2=1 step down (tests run every build).
Isa isa() {
#ifdef PAG_HAVE_X86_VARIANTS
  static const Isa v = [] {
    if (std::getenv("PAG_NO_AVX2") != nullptr || !__builtin_cpu_supports("avx2")) return Isa::base;
    const bool avx512 = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
                        __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq");
    return avx512 && std::getenv("PAG_NO_AVX512") == nullptr ? Isa::avx512 : Isa::avx2;
  }();
  return v;
#else
  return Isa::base;
#endif
}

// Runs CALL with `ns` naming the kernels' namespace for this CPU.
#ifdef PAG_HAVE_X86_VARIANTS
#define PAG_DISPATCH(CALL)                                                  \
  switch (isa()) {                                                          \
    case Isa::avx512: { namespace ns = avx512; CALL; } break;               \
    case Isa::avx2: { namespace ns = avx2; CALL; } break;                   \
    default: { namespace ns = base; CALL; } break;                          \
  }
#else
#define PAG_DISPATCH(CALL) { namespace ns = base; CALL; }
#endif

// The level arguments as the variant's own (layout-identical) struct.
template <class Args>
Args args_as(const base::LevelArgs& a) { return {a.x, a.n, a.table, a.shift, a.coef, a.mask}; }

template <class Fn>
void dispatch_features(int64_t f, Fn&& fn) {
  switch (f) {
    case 1: fn(std::integral_constant<int, 1>()); break;
    case 2: fn(std::integral_constant<int, 2>()); break;
    case 4: fn(std::integral_constant<int, 4>()); break;
    case 8: fn(std::integral_constant<int, 8>()); break;
    default: fn(std::integral_constant<int, 0>()); break;
  }
}

// One level's passes through the right instruction set and feature count.
enum class Kind { permuto, cubic };

void forward_level(Kind kind, const base::LevelArgs& a, int64_t F, float* out, float* jac) {
  dispatch_features(F, [&](auto fs) {
    constexpr int FS = decltype(fs)::value;
    if (kind == Kind::permuto) {
      PAG_DISPATCH((ns::forward_level<ns::Permuto, FS>(args_as<ns::LevelArgs>(a), (int)F, out, jac)))
    } else {
      PAG_DISPATCH((ns::forward_level<ns::Cubic, FS>(args_as<ns::LevelArgs>(a), (int)F, out, jac)))
    }
  });
}

void backward_level(Kind kind, const base::LevelArgs& a, int64_t F, const float* g, float* gtab, float* gxp) {
  dispatch_features(F, [&](auto fs) {
    constexpr int FS = decltype(fs)::value;
    if (kind == Kind::permuto) {
      PAG_DISPATCH((ns::backward_level<ns::Permuto, FS>(args_as<ns::LevelArgs>(a), (int)F, g, gtab, gxp)))
    } else {
      PAG_DISPATCH((ns::backward_level<ns::Cubic, FS>(args_as<ns::LevelArgs>(a), (int)F, g, gtab, gxp)))
    }
  });
}

void contract_level(int64_t n, int64_t F, const float* g, const float* jac, float* gxp) {
  dispatch_features(F, [&](auto fs) {
    constexpr int FS = decltype(fs)::value;
    PAG_DISPATCH((ns::contract_level<FS>(n, (int)F, g, jac, gxp)))
  });
}

// ---- memory: fresh multi-megabyte tensors cost a page fault per 4 KiB on every call (on these
// VMs about 20 ms for a 32 MiB table gradient, as much as the kernel itself). Outputs therefore
// come from a small process-wide pool of blocks returned by the tensors' deleters, and scratch
// buffers are kept per thread.

class BlockPool {
 public:
  static constexpr size_t kMaxCachedBytes = size_t(1) << 30;
  static constexpr size_t kMaxPerClass = 4;

  // Size classes 2^k * {4, 5, 6, 7} / 4 bound the waste to 25% when the batch size varies.
  static size_t size_class(size_t bytes) {
    size_t c = 4096;
    while (c < bytes) {
      if (c + c / 4 >= bytes) return c + c / 4;
      if (c + c / 2 >= bytes) return c + c / 2;
      if (c + 3 * (c / 4) >= bytes) return c + 3 * (c / 4);
      c *= 2;
    }
    return c;
  }

  void* get(size_t bytes) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      auto it = free_.find(bytes);
      if (it != free_.end() && !it->second.empty()) {
        void* p = it->second.back();
        it->second.pop_back();
        cached_ -= bytes;
        return p;
      }
    }
    void* p = std::aligned_alloc(64, bytes);
    if (!p) throw std::bad_alloc();
    return p;
  }

  void put(void* p, size_t bytes) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      auto& v = free_[bytes];
      if (v.size() < kMaxPerClass && cached_ + bytes <= kMaxCachedBytes) {
        v.push_back(p);
        cached_ += bytes;
        return;
      }
    }
    std::free(p);
  }

  // Frees every cached block (between a fit's phases and windows: the next one's sizes differ, and cached
  // blocks of the last one would sit beside its arrays). Returns the bytes freed.
  size_t release() {
    std::lock_guard<std::mutex> lock(mu_);
    const size_t freed = cached_;
    for (auto& kv : free_)
      for (void* p : kv.second) std::free(p);
    free_.clear();
    cached_ = 0;
    return freed;
  }

  size_t cached() {
    std::lock_guard<std::mutex> lock(mu_);
    return cached_;
  }

 private:
  std::mutex mu_;
  std::unordered_map<size_t, std::vector<void*>> free_;
  size_t cached_ = 0;
};

BlockPool& pool() {
  static BlockPool* p = new BlockPool();  // never destroyed: deleters may run during interpreter exit
  return *p;
}

torch::Tensor pooled_empty(at::IntArrayRef sizes) {
  int64_t numel = 1;
  for (int64_t s : sizes) numel *= s;
  if (numel * (int64_t)sizeof(float) < (int64_t(1) << 20)) return torch::empty(sizes, torch::kFloat32);
  const size_t bytes = BlockPool::size_class((size_t)numel * sizeof(float));
  void* p = pool().get(bytes);
  return torch::from_blob(p, sizes, [bytes](void* q) { pool().put(q, bytes); },
                          torch::TensorOptions().dtype(torch::kFloat32));
}

// Per-thread scratch that keeps its pages between calls.
thread_local std::vector<float> scratch_buf[3];

float* scratch(int slot, size_t n) {
  if (scratch_buf[slot].size() < n) scratch_buf[slot].resize(n);
  return scratch_buf[slot].data();
}

// The pool's cached blocks and the calling thread's scratch, freed; returns the bytes freed.
int64_t release_cached() {
  size_t freed = pool().release();
  for (auto& b : scratch_buf) {
    freed += b.capacity() * sizeof(float);
    std::vector<float>().swap(b);
  }
  return (int64_t)freed;
}

int64_t cached_bytes() { return (int64_t)pool().cached(); }

// The table is flat, [R, F]: level l's rows are offsets[l] .. offsets[l + 1] (a power of two of them, so
// the hash modulo is a mask). Returns the offsets as a host vector.
std::vector<int64_t> level_offsets(const torch::Tensor& offsets, int64_t L, const torch::Tensor& table) {
  TORCH_CHECK(offsets.device().is_cpu() && offsets.scalar_type() == torch::kInt64 && offsets.dim() == 1 &&
                  offsets.size(0) == L + 1, "offsets must be a CPU int64 [L + 1] tensor");
  const auto o = offsets.contiguous();
  std::vector<int64_t> off(o.data_ptr<int64_t>(), o.data_ptr<int64_t>() + L + 1);
  TORCH_CHECK(off[0] == 0 && off[L] == table.size(0), "offsets must run from 0 to the table's rows");
  for (int64_t l = 0; l < L; ++l) {
    const int64_t T = off[l + 1] - off[l];
    TORCH_CHECK(T > 0 && (T & (T - 1)) == 0 && T * table.size(1) < (int64_t(1) << 32),
                "each level's rows must be a power of two with rows * F < 2^32, got ", T, " at level ", l);
  }
  return off;
}

std::vector<int64_t> check(const torch::Tensor& x, const torch::Tensor& table, const torch::Tensor& offsets,
                           const torch::Tensor& coef, const torch::Tensor& shifts) {
  TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == torch::kFloat32 && x.dim() == 2 && x.size(1) == 3,
              "x must be a CPU float32 [N, 3] tensor, got ", x.sizes(), " ", x.scalar_type());
  TORCH_CHECK(table.device().is_cpu() && table.scalar_type() == torch::kFloat32 && table.dim() == 2,
              "table must be a CPU float32 [R, F] tensor, got ", table.sizes());
  TORCH_CHECK(coef.scalar_type() == torch::kFloat32 && coef.dim() == 2 && coef.size(1) == 3,
              "coef must be float32 [L, 3]");
  const int64_t L = coef.size(0);
  TORCH_CHECK(shifts.scalar_type() == torch::kFloat32 && shifts.dim() == 2 && shifts.size(0) == L &&
                  shifts.size(1) == 3, "shifts must be float32 [L, 3]");
  return level_offsets(offsets, L, table);
}

int threads_for(int64_t items) {
  return (int)std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), items));
}

// Rows i0..i1 of the longer of A and B (the points) of a [A, B, F] -> [B, A, F] transpose; each
// point's elements are read or written contiguously, each element (F floats) as one load and store.
template <int FS>
void transpose_rows(const float* __restrict src, float* __restrict dst, int64_t A, int64_t B, int64_t f_rt,
                    int64_t i0, int64_t i1) {
  const int64_t F = FS ? FS : f_rt;
  if (B >= A) {
    for (int64_t b = i0; b < i1; ++b)
      for (int64_t a = 0; a < A; ++a) std::memcpy(dst + (b * A + a) * F, src + (a * B + b) * F, sizeof(float) * F);
  } else {
    for (int64_t a = i0; a < i1; ++a)
      for (int64_t b = 0; b < B; ++b) std::memcpy(dst + (b * A + a) * F, src + (a * B + b) * F, sizeof(float) * F);
  }
}

// [A, B, F] -> [B, A, F] in parallel (the level-major scratch <-> the [N, L * F] layout).
void transpose_outer(const float* src, float* dst, int64_t A, int64_t B, int64_t F) {
  constexpr int64_t CHUNK = 256;
  const int64_t n = std::max(A, B), nchunks = (n + CHUNK - 1) / CHUNK;
  dispatch_features(F, [&](auto fs) {
    constexpr int FS = decltype(fs)::value;
#pragma omp parallel for num_threads(threads_for(nchunks / 16 + 1)) schedule(static)
    for (int64_t c = 0; c < nchunks; ++c)
      transpose_rows<FS>(src, dst, A, B, F, c * CHUNK, std::min(n, (c + 1) * CHUNK));
  });
}

// x [N, 3] -> blocked structure of arrays (block b: [3][BLOCK] at 3 * b * BLOCK, zero-padded), the
// layout the lattice code reads with plain vector loads, each coordinate clamped to [-bound, bound]
// and NaN made 0 on the way (torch.nan_to_num + clamp, without their passes over x and, in the
// backward, the masks of theirs that autograd would build). Kept in scratch slot 2.
const float* blocked_points(const torch::Tensor& x, float bound) {
  const int64_t N = x.size(0), nblocks = (N + BLOCK - 1) / BLOCK;
  float* xs = scratch(2, (size_t)(nblocks * 3 * BLOCK));
  const float* px = x.data_ptr<float>();
#pragma omp parallel for num_threads(threads_for(nblocks / 64 + 1)) schedule(static)
  for (int64_t b = 0; b < nblocks; ++b)
    for (int d = 0; d < 3; ++d)
      for (int64_t j = 0; j < BLOCK; ++j) {
        const int64_t n = b * BLOCK + j;
        const float v = n < N ? px[3 * n + d] : 0.f;
        xs[(b * 3 + d) * BLOCK + j] = v != v ? 0.f : std::min(std::max(v, -bound), bound);
      }
  return xs;
}

// Features [N, L * F] of x clamped to [-bound, bound]; with need_jac also d features / d x as
// [L, 3 F, N] (planes per level), which the backward contracts with grad_out instead of reading the
// table again.
std::vector<torch::Tensor> forward_impl(Kind kind, torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                        torch::Tensor coef, torch::Tensor shifts, bool need_jac, double bound) {
  const std::vector<int64_t> off = check(x, table, offsets, coef, shifts);
  x = x.contiguous(); table = table.contiguous(); coef = coef.contiguous(); shifts = shifts.contiguous();
  const int64_t N = x.size(0), L = coef.size(0), F = table.size(1);
  float* buf = scratch(0, (size_t)(L * N * F));  // [L, N, F]
  auto jac = need_jac ? pooled_empty({L, 3 * F, N}) : torch::Tensor();
  float* pj = need_jac ? jac.data_ptr<float>() : nullptr;
  const float* px = blocked_points(x, (float)bound);
  const float* pt = table.data_ptr<float>();
  const float* pc = coef.data_ptr<float>();
  const float* ps = shifts.data_ptr<float>();
#pragma omp parallel for num_threads(threads_for(L)) schedule(dynamic, 1)
  for (int64_t i = 0; i < L; ++i) {
    const int64_t l = L - 1 - i;  // finest (slowest) levels first: better balance at the end
    const uint32_t mask = (uint32_t)(off[l + 1] - off[l] - 1);
    forward_level(kind, base::LevelArgs{px, N, pt + off[l] * F, ps + 3 * l, pc + 3 * l, mask}, F, buf + l * N * F,
                  pj ? pj + l * 3 * F * N : nullptr);
  }
  auto out = pooled_empty({N, L * F});
  transpose_outer(buf, out.data_ptr<float>(), L, N, F);
  return {out, jac};
}

// (grad_table [R, F] or undefined, grad_x [N, 3] or undefined). grad_x comes from the forward's
// jac when given, else from reading the table rows again; it is 0 for the coordinates the forward
// clamped (outside [-bound, bound], or not finite), as through torch's clamp.
std::vector<torch::Tensor> backward_impl(Kind kind, torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                         torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts,
                                         std::optional<torch::Tensor> jac, bool need_table, bool need_x, double bound) {
  const std::vector<int64_t> off = check(x, table, offsets, coef, shifts);
  x = x.contiguous(); table = table.contiguous(); coef = coef.contiguous(); shifts = shifts.contiguous();
  const int64_t N = x.size(0), L = coef.size(0), F = table.size(1);
  TORCH_CHECK(grad_out.scalar_type() == torch::kFloat32 && grad_out.dim() == 2 && grad_out.size(0) == N &&
                  grad_out.size(1) == L * F, "grad_out must be float32 [N, L * F]");
  const bool use_jac = need_x && jac.has_value() && jac->defined();
  TORCH_CHECK(!use_jac || (jac->scalar_type() == torch::kFloat32 && jac->numel() == L * 3 * F * N),
              "jac must be the float32 [L, 3 F, N] Jacobian from the forward");
  grad_out = grad_out.contiguous();
  if (!need_table && !need_x) return {torch::Tensor(), torch::Tensor()};
  float* g = scratch(0, (size_t)(L * N * F));  // [L, N, F]
  transpose_outer(grad_out.data_ptr<float>(), g, N, L, F);
  const int nt = threads_for(L);
  // d/dx: one [3, N] partial sum per thread (levels run concurrently), added up at the end
  float* gx_parts = need_x ? scratch(1, (size_t)(nt * 3 * N)) : nullptr;
  if (need_x) std::memset(gx_parts, 0, sizeof(float) * nt * 3 * N);
  torch::Tensor jac_c = use_jac ? jac->contiguous() : torch::Tensor();
  const float* pj = use_jac ? jac_c.data_ptr<float>() : nullptr;
  auto gtable = need_table ? pooled_empty({table.size(0), F}) : torch::Tensor();
  float* pgt = need_table ? gtable.data_ptr<float>() : nullptr;
  const float* px = (gtable.defined() || !use_jac) ? blocked_points(x, (float)bound) : nullptr;
  const float* pt = table.data_ptr<float>();
  const float* pc = coef.data_ptr<float>();
  const float* ps = shifts.data_ptr<float>();
#pragma omp parallel num_threads(nt)
  {
    float* gxp = gx_parts ? gx_parts + (int64_t)omp_get_thread_num() * 3 * N : nullptr;
#pragma omp for schedule(dynamic, 1)
    for (int64_t i = 0; i < L; ++i) {
      const int64_t l = L - 1 - i, T = off[l + 1] - off[l];
      const uint32_t mask = (uint32_t)(T - 1);
      float* gl = pgt ? pgt + off[l] * F : nullptr;
      if (gl) std::memset(gl, 0, sizeof(float) * T * F);  // zeroed here, by its only writer, just before use
      if (gl || (gxp && !pj))
        backward_level(kind, base::LevelArgs{px, N, pt + off[l] * F, ps + 3 * l, pc + 3 * l, mask}, F,
                       g + l * N * F, gl, pj ? nullptr : gxp);
      if (gxp && pj) contract_level(N, F, g + l * N * F, pj + l * 3 * F * N, gxp);
    }
  }
  torch::Tensor gx;
  if (need_x) {
    gx = torch::empty({N, 3}, x.options());
    float* o = gx.data_ptr<float>();
    const float* xin = x.data_ptr<float>();
    const float b = (float)bound;
#pragma omp parallel for num_threads(threads_for(N / 4096 + 1)) schedule(static)
    for (int64_t n = 0; n < N; ++n)
      for (int d = 0; d < 3; ++d) {
        float v = 0.f;
        for (int t = 0; t < nt; ++t) v += gx_parts[((int64_t)t * 3 + d) * N + n];
        const float xv = xin[3 * n + d];
        o[3 * n + d] = (xv >= -b && xv <= b) ? v : 0.f;  // false for NaN
      }
  }
  return {gtable, gx};
}

}  // namespace

std::vector<torch::Tensor> permuto_forward(torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                           torch::Tensor coef, torch::Tensor shifts, bool need_jac, double bound) {
  return forward_impl(Kind::permuto, x, table, offsets, coef, shifts, need_jac, bound);
}

std::vector<torch::Tensor> permuto_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                            torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts,
                                            std::optional<torch::Tensor> jac, bool need_table, bool need_x,
                                            double bound) {
  return backward_impl(Kind::permuto, grad_out, x, table, offsets, coef, shifts, jac, need_table, need_x, bound);
}

std::vector<torch::Tensor> cubic_forward(torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                         torch::Tensor coef, torch::Tensor shifts, bool need_jac, double bound) {
  return forward_impl(Kind::cubic, x, table, offsets, coef, shifts, need_jac, bound);
}

std::vector<torch::Tensor> cubic_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                          torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts,
                                          std::optional<torch::Tensor> jac, bool need_table, bool need_x,
                                          double bound) {
  return backward_impl(Kind::cubic, grad_out, x, table, offsets, coef, shifts, jac, need_table, need_x, bound);
}

// Hashed rows and barycentric weights of one level's simplices, from the kernel's own code (the
// build this CPU runs; tests):
// x [N, 3], coef [3], shift [3] -> ([N, 4] int64, [N, 4] float32).
std::vector<torch::Tensor> permuto_simplices(torch::Tensor x, torch::Tensor coef, torch::Tensor shift, int64_t capacity) {
  TORCH_CHECK(x.scalar_type() == torch::kFloat32 && x.dim() == 2 && x.size(1) == 3, "x must be float32 [N, 3]");
  TORCH_CHECK(capacity > 0 && (capacity & (capacity - 1)) == 0, "capacity must be a power of two");
  x = x.contiguous(); coef = coef.contiguous(); shift = shift.contiguous();
  const int64_t N = x.size(0);
  auto rows = torch::empty({N, 4}, x.options().dtype(torch::kInt64));
  auto w = torch::empty({N, 4}, x.options());
  const float* xs = blocked_points(x, INFINITY);
  PAG_DISPATCH({
    ns::Permuto::Stage s;
    for (int64_t n0 = 0; n0 < N; n0 += BLOCK) {
      const int64_t nb = std::min<int64_t>(BLOCK, N - n0);
      ns::Permuto::locate(xs + 3 * n0, nb, shift.data_ptr<float>(), coef.data_ptr<float>(), (uint32_t)(capacity - 1), s);
      for (int64_t j = 0; j < nb; ++j)
        for (int k = 0; k < 4; ++k) {
          rows.data_ptr<int64_t>()[4 * (n0 + j) + k] = s.row[k][j];
          w.data_ptr<float>()[4 * (n0 + j) + k] = s.w[k][j];
        }
    }
  })
  return {rows, w};
}

// The machine's limit for this access pattern: per point and level, `reads` random reads and
// `updates` random read-modify-writes (into a scratch table) of F floats, in a table like `table`
// [R, F] with `offsets` [L + 1], scheduled like the kernels (one task per level, blocks of prefetched rows).
// Returns a checksum so that nothing is optimised away.
double random_access(torch::Tensor table, torch::Tensor offsets, int64_t n_points, int64_t reads, int64_t updates) {
  TORCH_CHECK(table.device().is_cpu() && table.scalar_type() == torch::kFloat32 && table.dim() == 2,
              "table must be a CPU float32 [R, F] tensor");
  TORCH_CHECK(reads >= 0 && updates >= 0 && reads + updates <= 16, "need 0 <= reads + updates <= 16");
  table = table.contiguous();
  const int64_t L = offsets.size(0) - 1, F = table.size(1);
  const std::vector<int64_t> off = level_offsets(offsets, L, table);
  auto upd = updates > 0 ? pooled_empty({table.size(0), F}) : torch::Tensor();
  const float* pt = table.data_ptr<float>();
  float* pu = updates > 0 ? upd.data_ptr<float>() : nullptr;
  const int64_t m = reads + updates;
  double total = 0.0;
#pragma omp parallel for num_threads(threads_for(L)) schedule(dynamic, 1) reduction(+ : total)
  for (int64_t l = 0; l < L; ++l) {
    const int64_t T = off[l + 1] - off[l];
    const uint32_t mask = (uint32_t)(T - 1);
    const float* tl = pt + off[l] * F;
    float* ul = pu ? pu + off[l] * F : nullptr;
    if (ul) std::memset(ul, 0, sizeof(float) * T * F);
    float s = 0.f;
    uint32_t off[2][BLOCK][16];
    auto locate = [&](int64_t n0, uint32_t (*o)[16]) {  // addresses of a block, prefetched
      const int64_t nb = std::min<int64_t>(BLOCK, n_points - n0);
      for (int64_t j = 0; j < nb; ++j)
        for (int64_t k = 0; k < m; ++k) {
          o[j][k] = base::hash3((int32_t)k, (int32_t)(n0 + j), (int32_t)l, mask) * (uint32_t)F;  // n scattered
          if (k < reads) __builtin_prefetch(tl + o[j][k]);
          else __builtin_prefetch(ul + o[j][k], 1);
        }
    };
    if (n_points > 0) locate(0, off[0]);
    int cur = 0;
    for (int64_t n0 = 0; n0 < n_points; n0 += BLOCK, cur ^= 1) {
      if (n0 + BLOCK < n_points) locate(n0 + BLOCK, off[cur ^ 1]);  // one block ahead, as the kernels
      const int64_t nb = std::min<int64_t>(BLOCK, n_points - n0);
      for (int64_t j = 0; j < nb; ++j) {
        for (int64_t k = 0; k < reads; ++k)
          for (int64_t f = 0; f < F; ++f) s += tl[off[cur][j][k] + f];
        for (int64_t k = reads; k < m; ++k)
          for (int64_t f = 0; f < F; ++f) ul[off[cur][j][k] + f] += 1.f;
      }
    }
    total += s;
  }
  return total;
}

#include "march_cpu.h"
#include "composite_cpu.h"
#include "ray_points_cpu.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("permuto_forward", &permuto_forward, "permutohedral hash encoding forward: (features, jacobian)");
  m.def("permuto_backward", &permuto_backward, "permutohedral hash encoding backward: (grad_table, grad_x)");
  m.def("cubic_forward", &cubic_forward, "cubic hash grid forward: (features, jacobian)");
  m.def("cubic_backward", &cubic_backward, "cubic hash grid backward: (grad_table, grad_x)");
  m.def("permuto_simplices", &permuto_simplices, "hashed rows and barycentric weights of one level");
  m.def("random_access", &random_access, "random read / read-modify-write microbenchmark");
  m.def("march_occupied", &march_occupied, "cone marching through the occupancy grid: (ray_index, col, t)");
  m.def("composite_forward", &composite_forward, "volume compositing of packed samples: (colour, depth, left)");
  m.def("composite_backward", &composite_backward, "its backward: (grad_sigma, grad_rgb)");
  m.def("ray_points_forward", &ray_points_forward, "sample points and unit directions of packed samples: (x, dn)");
  m.def("ray_points_backward", &ray_points_backward, "its backward: (grad_o, grad_d)");
  m.def("release_cached", &release_cached, "free the output pool's cached blocks and this thread's scratch: bytes");
  m.def("cached_bytes", &cached_bytes, "bytes of output blocks the pool holds for reuse");
}
