// CUDA kernels of the hash-grid encodings (the maths is in nerf/encoding.py; the CPU kernels are in
// permuto_cpu_kernels.h). Deliberately plain: one thread per (point, level), threads of a block
// share a level, atomicAdd for the table and position gradients. No torch headers here, so this
// file compiles with nvcc alone; permuto_cuda.cpp is the torch binding.
//
// Layout: x [N, 3], table [L, T, F] (T a power of two), coef and shifts [L, 3], out [N, L * F].
#include <cuda_runtime.h>

#include <cstdint>

namespace {

constexpr uint32_t P1 = 2654435761u;
constexpr uint32_t P2 = 805459861u;
constexpr int THREADS = 256;

__device__ __forceinline__ uint32_t hash3(int32_t a, int32_t b, int32_t c, uint32_t mask) {
  return ((uint32_t)a ^ ((uint32_t)b * P1) ^ ((uint32_t)c * P2)) & mask;
}

// The permutohedral simplex of one point: vertex rows, weights, ranks (as in the reference).
struct PermutoLat {
  static constexpr int V = 4;
  struct Aux { int rank[4]; };
  __device__ static void locate(const float* p, const float* sh, const float* cf, uint32_t mask, uint32_t row[4],
                                float w[4], Aux& aux) {
    const float c0 = __fmul_rn(__fadd_rn(p[0], sh[0]), cf[0]);
    const float c1 = __fmul_rn(__fadd_rn(p[1], sh[1]), cf[1]);
    const float c2 = __fmul_rn(__fadd_rn(p[2], sh[2]), cf[2]);
    const float e[4] = {__fadd_rn(__fadd_rn(c0, c1), c2), __fadd_rn(__fadd_rn(c1, c2), -c0),
                        __fadd_rn(c2, -__fmul_rn(2.f, c1)), __fmul_rn(-3.f, c2)};
    int q[4], rank[4], s = 0;
    float r[4];
    for (int i = 0; i < 4; ++i) {
      q[i] = __float2int_rn(__fmul_rn(e[i], 0.25f));  // nearest, ties to even (as the reference)
      r[i] = __fadd_rn(e[i], -(float)(4 * q[i]));
      s += q[i];
    }
    for (int i = 0; i < 4; ++i) rank[i] = s;
    for (int i = 0; i < 3; ++i)
      for (int j = i + 1; j < 4; ++j) {
        if (r[i] < r[j]) ++rank[i];
        else ++rank[j];
      }
    float b[5] = {0.f, 0.f, 0.f, 0.f, 0.f};
    int m[4];
    for (int i = 0; i < 4; ++i) {
      const int d = rank[i] < 0 ? 4 : (rank[i] > 3 ? -4 : 0);
      rank[i] += d;
      m[i] = 4 * q[i] + d;
      const float t = __fmul_rn(__fadd_rn(e[i], -(float)m[i]), 0.25f);
      b[3 - rank[i]] += t;
      b[4 - rank[i]] -= t;
    }
    w[0] = __fadd_rn(__fadd_rn(b[0], 1.f), b[4]);
    w[1] = b[1];
    w[2] = b[2];
    w[3] = b[3];
    for (int k = 0; k < 4; ++k)
      row[k] = hash3(m[0] + k - (rank[0] > 3 - k ? 4 : 0), m[1] + k - (rank[1] > 3 - k ? 4 : 0),
                     m[2] + k - (rank[2] > 3 - k ? 4 : 0), mask);
    for (int i = 0; i < 4; ++i) aux.rank[i] = rank[i];
  }
  // d loss / d x from dot_k = <grad_out, table row k>
  __device__ static void grad_x(const float dot[4], const Aux& aux, const float* cf, float gx[3]) {
    float de[4];
    for (int i = 0; i < 4; ++i) de[i] = 0.25f * (dot[3 - aux.rank[i]] - dot[(4 - aux.rank[i]) & 3]);
    gx[0] = (de[0] - de[1]) * cf[0];
    gx[1] = (de[0] + de[1] - 2.f * de[2]) * cf[1];
    gx[2] = (de[0] + de[1] + de[2] - 3.f * de[3]) * cf[2];
  }
};

// The cubic cell of one point: 8 corner rows, trilinear weights, fractions.
struct CubicLat {
  static constexpr int V = 8;
  struct Aux { float frac[3]; };
  __device__ static void locate(const float* p, const float* sh, const float* cf, uint32_t mask, uint32_t row[8],
                                float w[8], Aux& aux) {
    int i0[3];
    for (int d = 0; d < 3; ++d) {
      const float q = __fmul_rn(__fadd_rn(p[d], sh[d]), cf[d]);
      const float fl = floorf(q);
      i0[d] = (int)fl;
      aux.frac[d] = q - fl;
    }
    const float* f = aux.frac;
    for (int k = 0; k < 8; ++k) {
      const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
      w[k] = (dx ? f[0] : 1.f - f[0]) * (dy ? f[1] : 1.f - f[1]) * (dz ? f[2] : 1.f - f[2]);
      row[k] = hash3(i0[0] + dx, i0[1] + dy, i0[2] + dz, mask);
    }
  }
  __device__ static void grad_x(const float dot[8], const Aux& aux, const float* cf, float gx[3]) {
    const float* f = aux.frac;
    gx[0] = gx[1] = gx[2] = 0.f;
    for (int k = 0; k < 8; ++k) {
      const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
      const float wx = dx ? f[0] : 1.f - f[0], wy = dy ? f[1] : 1.f - f[1], wz = dz ? f[2] : 1.f - f[2];
      gx[0] += dot[k] * (dx ? 1.f : -1.f) * wy * wz;
      gx[1] += dot[k] * wx * (dy ? 1.f : -1.f) * wz;
      gx[2] += dot[k] * wx * wy * (dz ? 1.f : -1.f);
    }
    for (int d = 0; d < 3; ++d) gx[d] *= cf[d];
  }
};

template <class Lat>
__global__ void forward_kernel(const float* __restrict__ x, const float* __restrict__ table,
                               const int64_t* __restrict__ offsets, const float* __restrict__ coef,
                               const float* __restrict__ shifts, float* __restrict__ out, int64_t N, int64_t L,
                               int64_t F) {
  const int64_t idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (idx >= N * L) return;
  const int64_t l = idx / N, n = idx % N;  // consecutive threads: same level, consecutive points
  uint32_t row[Lat::V];
  float w[Lat::V];
  typename Lat::Aux aux;
  Lat::locate(x + 3 * n, shifts + 3 * l, coef + 3 * l, (uint32_t)(offsets[l + 1] - offsets[l] - 1), row, w, aux);
  const float* tl = table + offsets[l] * F;
  float* o = out + n * L * F + l * F;
  for (int64_t f = 0; f < F; ++f) {
    float acc = 0.f;
    for (int k = 0; k < Lat::V; ++k) acc += w[k] * __ldg(tl + (int64_t)row[k] * F + f);
    o[f] = acc;
  }
}

template <class Lat>
__global__ void backward_kernel(const float* __restrict__ grad_out, const float* __restrict__ x,
                                const float* __restrict__ table, const int64_t* __restrict__ offsets,
                                const float* __restrict__ coef, const float* __restrict__ shifts,
                                float* __restrict__ gtable, float* __restrict__ gx, int64_t N, int64_t L, int64_t F) {
  const int64_t idx = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (idx >= N * L) return;
  const int64_t l = idx / N, n = idx % N;
  uint32_t row[Lat::V];
  float w[Lat::V];
  typename Lat::Aux aux;
  Lat::locate(x + 3 * n, shifts + 3 * l, coef + 3 * l, (uint32_t)(offsets[l + 1] - offsets[l] - 1), row, w, aux);
  const float* g = grad_out + n * L * F + l * F;
  if (gtable) {
    float* gl = gtable + offsets[l] * F;
    for (int k = 0; k < Lat::V; ++k)
      for (int64_t f = 0; f < F; ++f) atomicAdd(gl + (int64_t)row[k] * F + f, w[k] * g[f]);
  }
  if (gx) {
    const float* tl = table + offsets[l] * F;
    float dot[Lat::V];
    for (int k = 0; k < Lat::V; ++k) {
      float d = 0.f;
      for (int64_t f = 0; f < F; ++f) d += g[f] * __ldg(tl + (int64_t)row[k] * F + f);
      dot[k] = d;
    }
    float gp[3];
    Lat::grad_x(dot, aux, coef + 3 * l, gp);
    for (int d = 0; d < 3; ++d) atomicAdd(gx + 3 * n + d, gp[d]);
  }
}

const char* status() {
  const cudaError_t err = cudaGetLastError();
  return err == cudaSuccess ? nullptr : cudaGetErrorString(err);
}

}  // namespace

// kind: 0 permutohedral, 1 cubic. Return nullptr, or the CUDA error message.
const char* pag_cuda_forward(int kind, const float* x, const float* table, const int64_t* offsets, const float* coef,
                             const float* shifts, float* out, int64_t N, int64_t L, int64_t F, void* stream) {
  const int64_t total = N * L;
  if (total == 0) return nullptr;
  const unsigned blocks = (unsigned)((total + THREADS - 1) / THREADS);
  cudaStream_t s = (cudaStream_t)stream;
  if (kind == 0) forward_kernel<PermutoLat><<<blocks, THREADS, 0, s>>>(x, table, offsets, coef, shifts, out, N, L, F);
  else forward_kernel<CubicLat><<<blocks, THREADS, 0, s>>>(x, table, offsets, coef, shifts, out, N, L, F);
  return status();
}

// gtable and gx must be zero-filled; either may be null.
const char* pag_cuda_backward(int kind, const float* grad_out, const float* x, const float* table,
                              const int64_t* offsets, const float* coef, const float* shifts, float* gtable,
                              float* gx, int64_t N, int64_t L, int64_t F, void* stream) {
  const int64_t total = N * L;
  if (total == 0 || (!gtable && !gx)) return nullptr;
  const unsigned blocks = (unsigned)((total + THREADS - 1) / THREADS);
  cudaStream_t s = (cudaStream_t)stream;
  if (kind == 0)
    backward_kernel<PermutoLat><<<blocks, THREADS, 0, s>>>(grad_out, x, table, offsets, coef, shifts, gtable, gx, N, L,
                                                           F);
  else
    backward_kernel<CubicLat><<<blocks, THREADS, 0, s>>>(grad_out, x, table, offsets, coef, shifts, gtable, gx, N, L,
                                                         F);
  return status();
}
