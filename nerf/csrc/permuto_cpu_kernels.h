// Per-level kernels of the CPU encodings (the maths is in nerf/encoding.py). Free of torch and
// OpenMP, and meant to be included INSIDE a namespace (no include guard, no includes of its own:
// the includer provides <algorithm> and <cstdint>), so permuto_cpu.cpp can compile it twice,
// for baseline x86-64 and for AVX2, and pick one at run time.
//
// A level pass walks the points in blocks. `locate` fills a block's Stage (structure of arrays)
// with a loop that has no data-dependent indexing, so the compiler vectorises it (selects, never
// arrays indexed by rank: GCC gives up on those); the block's table rows are prefetched, and the
// block is gathered or scattered DEPTH - 1 blocks later, so many random reads are in flight.
// BLOCK and DEPTH were tuned on 2-core Zen 1 VMs (2 MiB level tables, 512 KiB L2, 8 MiB L3) and
// rechecked on 2-core Sapphire Rapids VMs (2 MiB L2): DEPTH 2 is slower there, 4 no faster.

#ifndef PAG_BLOCK
#define PAG_BLOCK 16
#endif
#ifndef PAG_DEPTH
#define PAG_DEPTH 3
#endif
constexpr int BLOCK = PAG_BLOCK;  // points per pipeline stage
constexpr int DEPTH = PAG_DEPTH;  // stages in flight: rows are prefetched DEPTH - 1 blocks ahead

constexpr uint32_t P1 = 2654435761u;
constexpr uint32_t P2 = 805459861u;

inline uint32_t hash3(int32_t a, int32_t b, int32_t c, uint32_t mask) {
  return ((uint32_t)a ^ ((uint32_t)b * P1) ^ ((uint32_t)c * P2)) & mask;
}

// floor(v) for |v| < 2^31, vectorisable and without a libm call.
inline int32_t ifloor(float v) {
  const int32_t t = (int32_t)v;
  return t - (v < (float)t ? 1 : 0);
}

constexpr int FCHUNK = 8;  // features per pass of the Jacobian code

struct Permuto {
  static constexpr int V = 4;  // vertices per point
  struct Stage {
    uint32_t row[V][BLOCK];
    float w[V][BLOCK];
    int32_t rank[4][BLOCK];
    float val[V][FCHUNK][BLOCK];  // gathered table values (for the Jacobian)
  };

  // x: this block's points, blocked structure of arrays ([3][BLOCK], see LevelArgs).
  // Works in quarter units e = E / 4 (coef / 4: exact, scaling by a power of two commutes with
  // rounding), so rem0 / 4 = round(e) and t = e - rem0 / 4 cost no multiplies; the results are
  // bit-identical to the reference's.
  static void locate(const float* x, int64_t nb, const float* sh, const float* cf, uint32_t mask, Stage& s) {
    const float sh0 = sh[0], sh1 = sh[1], sh2 = sh[2];
    const float cq0 = 0.25f * cf[0], cq1 = 0.25f * cf[1], cq2 = 0.25f * cf[2];
    constexpr float MAGIC = 12582912.f;  // 1.5 * 2^23: (v + MAGIC) - MAGIC = v rounded, ties to even
    for (int64_t j = 0; j < nb; ++j) {
      const float c0 = (x[j] + sh0) * cq0;
      const float c1 = (x[BLOCK + j] + sh1) * cq1;
      const float c2 = (x[2 * BLOCK + j] + sh2) * cq2;
      const float e0 = c0 + c1 + c2, e1 = c1 + c2 - c0, e2 = c2 - 2.f * c1, e3 = -3.f * c2;
      const float q0 = (e0 + MAGIC) - MAGIC, q1 = (e1 + MAGIC) - MAGIC;  // rem0 = 4 q
      const float q2 = (e2 + MAGIC) - MAGIC, q3 = (e3 + MAGIC) - MAGIC;
      const float r0 = e0 - q0, r1 = e1 - q1, r2 = e2 - q2, r3 = e3 - q3;  // exact (Sterbenz)
      const int32_t S = (int32_t)((q0 + q1) + (q2 + q3));
      // k_i = S + #{j: r_j > r_i} + #{j < i: r_j == r_i}, in -2..5 (|S| <= 2)
      const int32_t l01 = r0 < r1, l02 = r0 < r2, l03 = r0 < r3, l12 = r1 < r2, l13 = r1 < r3, l23 = r2 < r3;
      const int32_t k0 = S + l01 + l02 + l03;
      const int32_t k1 = S + 1 - l01 + l12 + l13;
      const int32_t k2 = S + 2 - l02 - l12 + l23;
      const int32_t k3 = S + 3 - l03 - l13 - l23;
      // wrap: rank = k mod 4 while rem0 moves by -4 u, u = floor(k / 4) in {-1, 0, 1}
      const int32_t u0 = k0 >> 2, u1 = k1 >> 2, u2 = k2 >> 2, u3 = k3 >> 2;
      const int32_t k0w = k0 & 3, k1w = k1 & 3, k2w = k2 & 3, k3w = k3 & 3;
      // t_i = (E_i - rem0_i) / 4 = r_i + u_i (one rounding, as in the reference)
      const float t0 = r0 + (float)u0, t1 = r1 + (float)u1, t2 = r2 + (float)u2, t3 = r3 + (float)u3;
      // the ranks order the t descending, so t by rank is t sorted: a 5-comparator network
      const float a = std::max(t0, t1), b = std::min(t0, t1), c = std::max(t2, t3), d = std::min(t2, t3);
      const float lo = std::min(a, c), hi = std::max(b, d);
      const float s0 = std::max(a, c), s1 = std::max(lo, hi), s2 = std::min(lo, hi), s3 = std::min(b, d);
      // b[3 - rank_i] += t_i; b[4 - rank_i] -= t_i; w0 = (b0 + 1) + b4
      s.w[0][j] = (s3 + 1.f) + (-s0);
      s.w[1][j] = s2 - s3;
      s.w[2][j] = s1 - s2;
      s.w[3][j] = s0 - s1;
      // vertex k: key_i = rem0_i + k - 4 [rank_i > 3 - k]. The hash is linear in each key mod 2^32,
      // so the primes multiply rem0 once and the vertex offsets are constants.
      const uint32_t h0 = (uint32_t)(4 * ((int32_t)q0 - u0));
      const uint32_t h1 = (uint32_t)(4 * ((int32_t)q1 - u1)) * P1;
      const uint32_t h2 = (uint32_t)(4 * ((int32_t)q2 - u2)) * P2;
      s.row[0][j] = (h0 ^ h1 ^ h2) & mask;
      for (int k = 1; k < 4; ++k)
        s.row[k][j] = ((h0 + k - (k0w > 3 - k ? 4u : 0u)) ^ (h1 + k * P1 - (k1w > 3 - k ? 4u * P1 : 0u)) ^
                       (h2 + k * P2 - (k2w > 3 - k ? 4u * P2 : 0u))) & mask;
      s.rank[0][j] = k0w; s.rank[1][j] = k1w; s.rank[2][j] = k2w; s.rank[3][j] = k3w;
    }
  }

  // d feature_f / d x for a block and fc features (s.val), written to planes jac[d * F + f][n]
  // (n = point index, plane stride N). With the ranks fixed, d feature / d E_i =
  // (val[3 - rank_i] - val[(4 - rank_i) mod 4]) / 4, then through the elevation (steps 2 and 1).
  template <bool ACC>
  static void jacobian(const Stage& s, int64_t nb, int fc, const float* cf, float* jac, int64_t F, int64_t N) {
    const float cf0 = cf[0], cf1 = cf[1], cf2 = cf[2];
    for (int f = 0; f < fc; ++f) {
      float* j0 = jac + f * N;
      float* j1 = jac + (F + f) * N;
      float* j2 = jac + (2 * F + f) * N;
      for (int64_t j = 0; j < nb; ++j) {
        const float v0 = s.val[0][f][j], v1 = s.val[1][f][j], v2 = s.val[2][f][j], v3 = s.val[3][f][j];
        const float d0 = v3 - v0, d1 = v2 - v3, d2 = v1 - v2, d3 = v0 - v1;  // for rank 0, 1, 2, 3
        // d[rank_i], picked by the two bits of the rank (selects the compiler turns into blends)
        float e[4];
        for (int i = 0; i < 4; ++i) {
          const int32_t r = s.rank[i][j];
          const float lo = (r & 1) ? d1 : d0, hi = (r & 1) ? d3 : d2;
          e[i] = 0.25f * ((r & 2) ? hi : lo);
        }
        const float e0 = e[0], e1 = e[1], e2 = e[2], e3 = e[3];
        // E0 = c0+c1+c2, E1 = -c0+c1+c2, E2 = -2c1+c2, E3 = -3c2: d/dc = transpose
        const float g0 = (e0 - e1) * cf0, g1 = (e0 + e1 - 2.f * e2) * cf1, g2 = (e0 + e1 + e2 - 3.f * e3) * cf2;
        j0[j] = ACC ? j0[j] + g0 : g0;
        j1[j] = ACC ? j1[j] + g1 : g1;
        j2[j] = ACC ? j2[j] + g2 : g2;
      }
    }
  }
};

struct Cubic {
  static constexpr int V = 8;
  struct Stage {
    uint32_t row[V][BLOCK];
    float w[V][BLOCK];
    float frac[3][BLOCK];
    float val[V][FCHUNK][BLOCK];
  };

  static void locate(const float* x, int64_t nb, const float* sh, const float* cf, uint32_t mask, Stage& s) {
    for (int64_t j = 0; j < nb; ++j) {
      int32_t i0[3];
      float fr[3];
      for (int d = 0; d < 3; ++d) {
        const float q = (x[d * BLOCK + j] + sh[d]) * cf[d];
        i0[d] = ifloor(q);
        fr[d] = q - (float)i0[d];
        s.frac[d][j] = fr[d];
      }
      // the hash is linear in each key mod 2^32: the primes multiply the cell's corner once
      const uint32_t hx = (uint32_t)i0[0], hy = (uint32_t)i0[1] * P1, hz = (uint32_t)i0[2] * P2;
      for (int k = 0; k < 8; ++k) {
        const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
        s.w[k][j] = (dx ? fr[0] : 1.f - fr[0]) * (dy ? fr[1] : 1.f - fr[1]) * (dz ? fr[2] : 1.f - fr[2]);
        s.row[k][j] = ((hx + dx) ^ (hy + (dy ? P1 : 0u)) ^ (hz + (dz ? P2 : 0u))) & mask;
      }
    }
  }

  // d feature_f / d x for a block: the derivative of the trilinear weights times the cell factor.
  template <bool ACC>
  static void jacobian(const Stage& s, int64_t nb, int fc, const float* cf, float* jac, int64_t F, int64_t N) {
    float dw[3][V][BLOCK];
    for (int64_t j = 0; j < nb; ++j) {
      const float fx = s.frac[0][j], fy = s.frac[1][j], fz = s.frac[2][j];
      for (int k = 0; k < 8; ++k) {
        const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
        const float wx = dx ? fx : 1.f - fx, wy = dy ? fy : 1.f - fy, wz = dz ? fz : 1.f - fz;
        dw[0][k][j] = (dx ? 1.f : -1.f) * wy * wz * cf[0];
        dw[1][k][j] = wx * (dy ? 1.f : -1.f) * wz * cf[1];
        dw[2][k][j] = wx * wy * (dz ? 1.f : -1.f) * cf[2];
      }
    }
    for (int d = 0; d < 3; ++d)
      for (int f = 0; f < fc; ++f) {
        float* jd = jac + (d * F + f) * N;
        for (int64_t j = 0; j < nb; ++j) {
          float acc = 0.f;
          for (int k = 0; k < 8; ++k) acc += dw[d][k][j] * s.val[k][f][j];
          jd[j] = ACC ? jd[j] + acc : acc;
        }
      }
  }
};

// Runs prepare(block) DEPTH - 1 blocks ahead of consume(block) over n points; both get the block's
// first point and its stage slot.
template <class Prepare, class Consume>
void pipeline(int64_t n, Prepare&& prepare, Consume&& consume) {
  const int64_t nblocks = (n + BLOCK - 1) / BLOCK;
  for (int64_t b = 0; b < std::min<int64_t>(DEPTH - 1, nblocks); ++b) prepare(b * BLOCK, (int)(b % DEPTH));
  for (int64_t b = 0; b < nblocks; ++b) {
    if (b + DEPTH - 1 < nblocks) prepare((b + DEPTH - 1) * BLOCK, (int)((b + DEPTH - 1) % DEPTH));
    consume(b * BLOCK, (int)(b % DEPTH));
  }
}

struct LevelArgs {
  const float* x;      // points in blocked structure of arrays: block b = points b*BLOCK.. is [3][BLOCK]
                       // at x + 3 * b * BLOCK (padded to whole blocks)
  int64_t n;
  const float* table;  // this level's [T, F]
  const float* shift;  // [3]
  const float* coef;   // [3]
  uint32_t mask;
};

// Features of one level: out [N, F]; with jac != null also d feature / d x as planes jac [3 F, N].
template <class Lat, int FS>
void forward_level(const LevelArgs& a, int f_rt, float* out, float* jac) {
  const int F = FS ? FS : f_rt;
  constexpr int V = Lat::V;
  typename Lat::Stage st[DEPTH];
  auto locate = [&](int64_t n0, typename Lat::Stage& s) {
    const int64_t nb = std::min<int64_t>(BLOCK, a.n - n0);
    Lat::locate(a.x + 3 * n0, nb, a.shift, a.coef, a.mask, s);
    for (int k = 0; k < V; ++k)
      for (int64_t j = 0; j < nb; ++j) __builtin_prefetch(a.table + (size_t)s.row[k][j] * F);
  };
  auto gather = [&](int64_t n0, typename Lat::Stage& s) {
    const int64_t nb = std::min<int64_t>(BLOCK, a.n - n0);
    const int fc0 = jac ? std::min(F, FCHUNK) : 0;
    for (int64_t j = 0; j < nb; ++j) {
      const float* rows[V];
      for (int k = 0; k < V; ++k) rows[k] = a.table + (size_t)s.row[k][j] * F;
      float* o = out + (n0 + j) * F;
      for (int f = 0; f < F; ++f) {
        float acc = s.w[0][j] * rows[0][f];
        for (int k = 1; k < V; ++k) acc += s.w[k][j] * rows[k][f];
        o[f] = acc;
      }
      for (int f = 0; f < fc0; ++f)  // keep the values, structure-of-arrays, for the Jacobian
        for (int k = 0; k < V; ++k) s.val[k][f][j] = rows[k][f];
    }
    if (!jac) return;
    Lat::template jacobian<false>(s, nb, fc0, a.coef, jac + n0, F, a.n);
    for (int f0 = FCHUNK; f0 < F; f0 += FCHUNK) {  // more than FCHUNK features: the rows are in L1 still
      const int fc = std::min(FCHUNK, F - f0);
      for (int64_t j = 0; j < nb; ++j)
        for (int k = 0; k < V; ++k) {
          const float* r = a.table + (size_t)s.row[k][j] * F + f0;
          for (int f = 0; f < fc; ++f) s.val[k][f][j] = r[f];
        }
      Lat::template jacobian<false>(s, nb, fc, a.coef, jac + f0 * a.n + n0, F, a.n);
    }
  };
  pipeline(a.n, [&](int64_t n0, int i) { locate(n0, st[i]); }, [&](int64_t n0, int i) { gather(n0, st[i]); });
}

// Backward of one level: gtab [T, F] += w_k * g [N, F] at each vertex row (if gtab), and, if gxp,
// d loss / d x accumulated into gxp [3, N] by reading the table rows again (the alternative to the
// forward's Jacobian): with dot_k = <g, row k>, the Jacobian code applied to one "feature" dot.
template <class Lat, int FS>
void backward_level(const LevelArgs& a, int f_rt, const float* g, float* gtab, float* gxp) {
  const int F = FS ? FS : f_rt;
  constexpr int V = Lat::V;
  typename Lat::Stage st[DEPTH];
  auto locate = [&](int64_t n0, typename Lat::Stage& s) {
    const int64_t nb = std::min<int64_t>(BLOCK, a.n - n0);
    Lat::locate(a.x + 3 * n0, nb, a.shift, a.coef, a.mask, s);
    for (int k = 0; k < V; ++k)
      for (int64_t j = 0; j < nb; ++j) {
        if (gtab) __builtin_prefetch(gtab + (size_t)s.row[k][j] * F, 1);
        if (gxp) __builtin_prefetch(a.table + (size_t)s.row[k][j] * F);
      }
  };
  auto scatter = [&](int64_t n0, typename Lat::Stage& s) {
    const int64_t nb = std::min<int64_t>(BLOCK, a.n - n0);
    for (int64_t j = 0; j < nb; ++j) {
      const float* gj = g + (n0 + j) * F;
      if (gtab)
        for (int k = 0; k < V; ++k) {
          float* rk = gtab + (size_t)s.row[k][j] * F;
          for (int f = 0; f < F; ++f) rk[f] += s.w[k][j] * gj[f];
        }
      if (gxp)
        for (int k = 0; k < V; ++k) {
          const float* rk = a.table + (size_t)s.row[k][j] * F;
          float d = 0.f;
          for (int f = 0; f < F; ++f) d += gj[f] * rk[f];
          s.val[k][0][j] = d;
        }
    }
    if (gxp) Lat::template jacobian<true>(s, nb, 1, a.coef, gxp + n0, 1, a.n);
  };
  pipeline(a.n, [&](int64_t n0, int i) { locate(n0, st[i]); }, [&](int64_t n0, int i) { scatter(n0, st[i]); });
}

// d loss / d x contribution of one level: gxp [3, N] += sum_f g [N, F] * jac [3 F, N].
template <int FS>
void contract_level(int64_t n, int f_rt, const float* g, const float* jac, float* gxp) {
  const int F = FS ? FS : f_rt;
  for (int64_t i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) {
      float acc = gxp[d * n + i];
      for (int f = 0; f < F; ++f) acc += g[i * F + f] * jac[(d * F + f) * n + i];
      gxp[d * n + i] = acc;
    }
}
