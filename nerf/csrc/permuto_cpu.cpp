// Fused CPU kernels (OpenMP) for the multi-resolution permutohedral hash encoding, a cubic
// (trilinear, 8-corner) hash grid written with the same care for comparison, and a random-read
// microbenchmark giving the machine's limit. The maths is documented in nerf/encoding.py; the
// pure-torch reference there is what the tests compare these kernels against.
//
// Layout: x [N, 3] float32, table [L, T, F] float32 (T a power of two), scales [L], shifts [L, 3];
// output [N, L * F] level-major. Loops run level-major so one level's table stays in cache while
// all points pass; the table gradient uses one buffer per thread for the current level only.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <omp.h>

#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr uint32_t P1 = 2654435761u;
constexpr uint32_t P2 = 805459861u;
constexpr int64_t BLOCK = 16;

inline uint32_t hash3(int32_t a, int32_t b, int32_t c, uint32_t mask) {
  return ((uint32_t)a ^ ((uint32_t)b * P1) ^ ((uint32_t)c * P2)) & mask;
}

// One point at one level of the permutohedral lattice: the 4 hashed vertices, their barycentric
// weights, and (optionally) d(weights)/d(elevated coords) encoded by the ranks.
struct Simplex {
  uint32_t idx[4];
  float w[4];
  int rank[4];
};

inline void simplex(const float* p, const float* shift, float inv_scale, uint32_t mask, Simplex& s) {
  // c_i = (p_i + r_i) / (sqrt((i+1)(i+2)) sigma)
  const float c0 = (p[0] + shift[0]) * inv_scale * 0.70710678f;  // 1/sqrt(2)
  const float c1 = (p[1] + shift[1]) * inv_scale * 0.40824829f;  // 1/sqrt(6)
  const float c2 = (p[2] + shift[2]) * inv_scale * 0.28867513f;  // 1/sqrt(12)
  float e[4] = {c0 + c1 + c2, c1 + c2 - c0, c2 - 2.f * c1, -3.f * c2};
  int rem0[4];
  float r[4];
  int sum = 0;
  for (int i = 0; i < 4; ++i) {
    rem0[i] = 4 * (int)std::nearbyint(e[i] * 0.25f);  // nearest multiple of 4, ties to even
    sum += rem0[i];
    r[i] = e[i] - (float)rem0[i];
  }
  int rank[4] = {0, 0, 0, 0};
  for (int i = 0; i < 3; ++i)
    for (int j = i + 1; j < 4; ++j) {
      if (r[i] < r[j]) ++rank[i]; else ++rank[j];
    }
  const int S = sum / 4;
  for (int i = 0; i < 4; ++i) {
    rank[i] += S;
    if (rank[i] < 0) { rank[i] += 4; rem0[i] += 4; }
    else if (rank[i] > 3) { rank[i] -= 4; rem0[i] -= 4; }
  }
  float b[5] = {0.f, 0.f, 0.f, 0.f, 0.f};
  for (int i = 0; i < 4; ++i) {
    const float t = (e[i] - (float)rem0[i]) * 0.25f;
    b[3 - rank[i]] += t;
    b[4 - rank[i]] -= t;
  }
  b[0] += 1.f + b[4];
  for (int k = 0; k < 4; ++k) {
    int key[3];
    for (int i = 0; i < 3; ++i) key[i] = rem0[i] + k - ((rank[i] > 3 - k) ? 4 : 0);
    s.idx[k] = hash3(key[0], key[1], key[2], mask);
    s.w[k] = b[k];
  }
  for (int i = 0; i < 4; ++i) s.rank[i] = rank[i];
}

inline int nthreads() { return std::max(1, at::get_num_threads()); }

void check(const torch::Tensor& x, const torch::Tensor& table, const torch::Tensor& scales,
           const torch::Tensor& shifts) {
  TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == torch::kFloat32 && x.dim() == 2 && x.size(1) == 3,
              "x must be a CPU float32 [N, 3] tensor");
  TORCH_CHECK(table.scalar_type() == torch::kFloat32 && table.dim() == 3, "table must be float32 [L, T, F]");
  const int64_t T = table.size(1);
  TORCH_CHECK(T > 0 && (T & (T - 1)) == 0, "table capacity must be a power of two");
  TORCH_CHECK(scales.size(0) == table.size(0) && shifts.size(0) == table.size(0), "one scale/shift per level");
}

}  // namespace

torch::Tensor permuto_forward(torch::Tensor x, torch::Tensor table, torch::Tensor scales, torch::Tensor shifts) {
  check(x, table, scales, shifts);
  x = x.contiguous(); table = table.contiguous();
  const int64_t N = x.size(0), L = table.size(0), T = table.size(1), F = table.size(2);
  auto out = torch::empty({N, L * F}, x.options());
  const float* px = x.data_ptr<float>();
  const float* pt = table.data_ptr<float>();
  const float* ps = scales.contiguous().data_ptr<float>();
  const float* psh = shifts.contiguous().data_ptr<float>();
  float* po = out.data_ptr<float>();
  const uint32_t mask = (uint32_t)(T - 1);
  const int nt = nthreads();
  for (int64_t l = 0; l < L; ++l) {
    const float inv = 1.f / ps[l];
    const float* tl = pt + l * T * F;
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t n0 = 0; n0 < N; n0 += BLOCK) {
      // Compute a block of simplices first and prefetch their rows, so many table reads are in
      // flight at once (the loop is bound by random-read latency, not arithmetic).
      Simplex s[BLOCK];
      const int64_t nb = std::min<int64_t>(BLOCK, N - n0);
      for (int64_t j = 0; j < nb; ++j) {
        simplex(px + 3 * (n0 + j), psh + 3 * l, inv, mask, s[j]);
        for (int k = 0; k < 4; ++k) __builtin_prefetch(tl + (int64_t)s[j].idx[k] * F);
      }
      for (int64_t j = 0; j < nb; ++j) {
        float* o = po + (n0 + j) * L * F + l * F;
        for (int64_t f = 0; f < F; ++f) o[f] = 0.f;
        for (int k = 0; k < 4; ++k) {
          const float* row = tl + (int64_t)s[j].idx[k] * F;
          for (int64_t f = 0; f < F; ++f) o[f] += s[j].w[k] * row[f];
        }
      }
    }
  }
  return out;
}

std::vector<torch::Tensor> permuto_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                            torch::Tensor scales, torch::Tensor shifts, bool need_table,
                                            bool need_x) {
  check(x, table, scales, shifts);
  x = x.contiguous(); table = table.contiguous(); grad_out = grad_out.contiguous();
  const int64_t N = x.size(0), L = table.size(0), T = table.size(1), F = table.size(2);
  auto gtable = need_table ? torch::zeros_like(table) : torch::Tensor();
  auto gx = need_x ? torch::zeros_like(x) : torch::Tensor();
  const float* px = x.data_ptr<float>();
  const float* pt = table.data_ptr<float>();
  const float* pg = grad_out.data_ptr<float>();
  const float* ps = scales.contiguous().data_ptr<float>();
  const float* psh = shifts.contiguous().data_ptr<float>();
  float* pgt = need_table ? gtable.data_ptr<float>() : nullptr;
  float* pgx = need_x ? gx.data_ptr<float>() : nullptr;
  const uint32_t mask = (uint32_t)(T - 1);
  const int nt = nthreads();
  std::vector<float> buffers(need_table && nt > 1 ? (size_t)(nt - 1) * T * F : 0);
  for (int64_t l = 0; l < L; ++l) {
    const float inv = 1.f / ps[l];
    const float* tl = pt + l * T * F;
    float* gl = need_table ? pgt + l * T * F : nullptr;
    const float dc[3] = {inv * 0.70710678f, inv * 0.40824829f, inv * 0.28867513f};
#pragma omp parallel num_threads(nt)
    {
      const int tid = omp_get_thread_num();
      float* acc = nullptr;
      if (need_table) {
        acc = tid == 0 ? gl : buffers.data() + (size_t)(tid - 1) * T * F;
        if (tid > 0) std::fill(acc, acc + T * F, 0.f);
      }
#pragma omp for schedule(static)
      for (int64_t n0 = 0; n0 < N; n0 += BLOCK) {
        Simplex sb[BLOCK];
        const int64_t nb = std::min<int64_t>(BLOCK, N - n0);
        for (int64_t j = 0; j < nb; ++j) {
          simplex(px + 3 * (n0 + j), psh + 3 * l, inv, mask, sb[j]);
          for (int k = 0; k < 4; ++k) {
            if (need_table) __builtin_prefetch(acc + (int64_t)sb[j].idx[k] * F, 1);
            if (need_x) __builtin_prefetch(tl + (int64_t)sb[j].idx[k] * F);
          }
        }
        for (int64_t j = 0; j < nb; ++j) {
        const int64_t n = n0 + j;
        const Simplex& s = sb[j];
        const float* g = pg + n * L * F + l * F;
        if (need_table) {
          for (int k = 0; k < 4; ++k) {
            float* row = acc + (int64_t)s.idx[k] * F;
            for (int64_t f = 0; f < F; ++f) row[f] += s.w[k] * g[f];
          }
        }
        if (need_x) {
          // d feature / d E_i = (T[v_{3-rank_i}] - T[v_{(4-rank_i) mod 4}]) / 4, dotted with grad_out
          float dE[4];
          for (int i = 0; i < 4; ++i) {
            const int a = 3 - s.rank[i], b = (4 - s.rank[i]) & 3;
            const float* ra = tl + (int64_t)s.idx[a] * F;
            const float* rb = tl + (int64_t)s.idx[b] * F;
            float d = 0.f;
            for (int64_t f = 0; f < F; ++f) d += g[f] * (ra[f] - rb[f]);
            dE[i] = 0.25f * d;
          }
          // E0 = c0+c1+c2, E1 = -c0+c1+c2, E2 = -2c1+c2, E3 = -3c2
          const float dc0 = dE[0] - dE[1];
          const float dc1 = dE[0] + dE[1] - 2.f * dE[2];
          const float dc2 = dE[0] + dE[1] + dE[2] - 3.f * dE[3];
          float* o = pgx + 3 * n;
          o[0] += dc0 * dc[0];
          o[1] += dc1 * dc[1];
          o[2] += dc2 * dc[2];
        }
        }
      }
      if (need_table && nt > 1) {
#pragma omp barrier
#pragma omp for schedule(static)
        for (int64_t i = 0; i < T * F; ++i) {
          float v = 0.f;
          for (int t = 0; t < nt - 1; ++t) v += buffers[(size_t)t * T * F + i];
          gl[i] += v;
        }
      }
    }
  }
  return {gtable, gx};
}

// ---- cubic (trilinear, 8 corners) hash grid, same layout and care ------------------------------

torch::Tensor cubic_forward(torch::Tensor x, torch::Tensor table, torch::Tensor scales, torch::Tensor shifts) {
  check(x, table, scales, shifts);
  x = x.contiguous(); table = table.contiguous();
  const int64_t N = x.size(0), L = table.size(0), T = table.size(1), F = table.size(2);
  auto out = torch::empty({N, L * F}, x.options());
  const float* px = x.data_ptr<float>();
  const float* pt = table.data_ptr<float>();
  const float* ps = scales.contiguous().data_ptr<float>();
  const float* psh = shifts.contiguous().data_ptr<float>();
  float* po = out.data_ptr<float>();
  const uint32_t mask = (uint32_t)(T - 1);
  const int nt = nthreads();
  for (int64_t l = 0; l < L; ++l) {
    const float inv = 1.f / ps[l];
    const float* tl = pt + l * T * F;
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
      float q[3], f[3];
      int32_t i0[3];
      for (int d = 0; d < 3; ++d) {
        q[d] = (px[3 * n + d] + psh[3 * l + d]) * inv;
        const float fl = std::floor(q[d]);
        i0[d] = (int32_t)fl;
        f[d] = q[d] - fl;
      }
      float* o = po + n * L * F + l * F;
      for (int64_t c = 0; c < F; ++c) o[c] = 0.f;
      for (int k = 0; k < 8; ++k) {
        const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
        const float w = (dx ? f[0] : 1.f - f[0]) * (dy ? f[1] : 1.f - f[1]) * (dz ? f[2] : 1.f - f[2]);
        const float* row = tl + (int64_t)hash3(i0[0] + dx, i0[1] + dy, i0[2] + dz, mask) * F;
        for (int64_t c = 0; c < F; ++c) o[c] += w * row[c];
      }
    }
  }
  return out;
}

std::vector<torch::Tensor> cubic_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                          torch::Tensor scales, torch::Tensor shifts, bool need_table, bool need_x) {
  check(x, table, scales, shifts);
  x = x.contiguous(); table = table.contiguous(); grad_out = grad_out.contiguous();
  const int64_t N = x.size(0), L = table.size(0), T = table.size(1), F = table.size(2);
  auto gtable = need_table ? torch::zeros_like(table) : torch::Tensor();
  auto gx = need_x ? torch::zeros_like(x) : torch::Tensor();
  const float* px = x.data_ptr<float>();
  const float* pt = table.data_ptr<float>();
  const float* pg = grad_out.data_ptr<float>();
  const float* ps = scales.contiguous().data_ptr<float>();
  const float* psh = shifts.contiguous().data_ptr<float>();
  float* pgt = need_table ? gtable.data_ptr<float>() : nullptr;
  float* pgx = need_x ? gx.data_ptr<float>() : nullptr;
  const uint32_t mask = (uint32_t)(T - 1);
  const int nt = nthreads();
  std::vector<float> buffers(need_table && nt > 1 ? (size_t)(nt - 1) * T * F : 0);
  for (int64_t l = 0; l < L; ++l) {
    const float inv = 1.f / ps[l];
    const float* tl = pt + l * T * F;
    float* gl = need_table ? pgt + l * T * F : nullptr;
#pragma omp parallel num_threads(nt)
    {
      const int tid = omp_get_thread_num();
      float* acc = nullptr;
      if (need_table) {
        acc = tid == 0 ? gl : buffers.data() + (size_t)(tid - 1) * T * F;
        if (tid > 0) std::fill(acc, acc + T * F, 0.f);
      }
#pragma omp for schedule(static)
      for (int64_t n = 0; n < N; ++n) {
        float f[3];
        int32_t i0[3];
        for (int d = 0; d < 3; ++d) {
          const float q = (px[3 * n + d] + psh[3 * l + d]) * inv;
          const float fl = std::floor(q);
          i0[d] = (int32_t)fl;
          f[d] = q - fl;
        }
        const float* g = pg + n * L * F + l * F;
        float gxl[3] = {0.f, 0.f, 0.f};
        for (int k = 0; k < 8; ++k) {
          const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
          const float wx = dx ? f[0] : 1.f - f[0], wy = dy ? f[1] : 1.f - f[1], wz = dz ? f[2] : 1.f - f[2];
          const uint32_t h = hash3(i0[0] + dx, i0[1] + dy, i0[2] + dz, mask);
          if (need_table) {
            float* row = acc + (int64_t)h * F;
            const float w = wx * wy * wz;
            for (int64_t c = 0; c < F; ++c) row[c] += w * g[c];
          }
          if (need_x) {
            const float* row = tl + (int64_t)h * F;
            float d = 0.f;
            for (int64_t c = 0; c < F; ++c) d += g[c] * row[c];
            gxl[0] += d * (dx ? 1.f : -1.f) * wy * wz;
            gxl[1] += d * wx * (dy ? 1.f : -1.f) * wz;
            gxl[2] += d * wx * wy * (dz ? 1.f : -1.f);
          }
        }
        if (need_x) for (int d = 0; d < 3; ++d) pgx[3 * n + d] += gxl[d] * inv;
      }
      if (need_table && nt > 1) {
#pragma omp barrier
#pragma omp for schedule(static)
        for (int64_t i = 0; i < T * F; ++i) {
          float v = 0.f;
          for (int t = 0; t < nt - 1; ++t) v += buffers[(size_t)t * T * F + i];
          gl[i] += v;
        }
      }
    }
  }
  return {gtable, gx};
}

// The machine's limit: `reads` dependent-free random reads of F floats per point-level from a
// table of the same size, summed so the compiler cannot drop them. Returns the checksum.
double random_reads(int64_t n_points, int64_t n_levels, int64_t capacity, int64_t n_features, int64_t reads) {
  std::vector<float> table((size_t)n_levels * capacity * n_features, 1.f);
  const uint32_t mask = (uint32_t)(capacity - 1);
  double total = 0.0;
  const int nt = nthreads();
  for (int64_t l = 0; l < n_levels; ++l) {
    const float* tl = table.data() + l * capacity * n_features;
#pragma omp parallel for num_threads(nt) reduction(+ : total) schedule(static)
    for (int64_t n = 0; n < n_points; ++n) {
      float s = 0.f;
      for (int64_t k = 0; k < reads; ++k) {
        const uint32_t h = hash3((int32_t)k, (int32_t)n, (int32_t)(l + 7 * k), mask);  // n scattered by the prime
        for (int64_t f = 0; f < n_features; ++f) s += tl[(int64_t)h * n_features + f];
      }
      total += s;
    }
  }
  return total;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("permuto_forward", &permuto_forward, "permutohedral hash encoding forward");
  m.def("permuto_backward", &permuto_backward, "permutohedral hash encoding backward");
  m.def("cubic_forward", &cubic_forward, "cubic hash grid forward");
  m.def("cubic_backward", &cubic_backward, "cubic hash grid backward");
  m.def("random_reads", &random_reads, "random-read microbenchmark");
}
