// Fused cone marching through the occupancy grid (CPU, OpenMP over rays), included by permuto_cpu.cpp.
//
// The torch reference is nerf/render.py: candidates() (depths between the edges, occupied cells) and
// pack() (the occupied candidates ranked [first, first + max_per_ray) per ray, packed). This kernel
// does both without the [R, S, 3] point tensor and the [R, S] masks: one pass per ray keeps its
// samples in a scratch row, a prefix sum places every ray's run, a copy packs them. The arithmetic is
// the reference's, operation for operation (built with -ffp-contract=off), so the samples are equal.
//
// Inputs: origins, dirs [R, 3] float32; edges [S + 1] float32; u [R, S] float32 jitter in [0, 1)
// (undefined = mid-points, 0.5); occupied [nx * ny * nz] bool (x-major, as OccupancyGrid.index);
// lo, cell [3] float32; res [3] int64; t_max [R] float32 (undefined = none).
// Output: ray_index [K] int64, col [K] int64 (candidate index), t [K] float32; rays in order, then depth.

std::vector<torch::Tensor> march_occupied(torch::Tensor origins, torch::Tensor dirs, torch::Tensor edges,
                                          c10::optional<torch::Tensor> u_opt, torch::Tensor occupied,
                                          torch::Tensor lo, torch::Tensor cell, torch::Tensor res,
                                          c10::optional<torch::Tensor> t_max_opt, int64_t first,
                                          int64_t max_per_ray) {
  auto f32 = [](const torch::Tensor& t, const char* name, int64_t n) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32 && t.is_contiguous() && t.numel() == n,
                "march_occupied: ", name, " must be a contiguous CPU float32 tensor of ", n, " values");
  };
  const int64_t R = origins.size(0);
  const int64_t S = edges.numel() - 1;
  TORCH_CHECK(S >= 0 && origins.dim() == 2 && origins.size(1) == 3, "march_occupied: origins must be [R, 3]");
  f32(origins, "origins", R * 3);
  f32(dirs, "dirs", R * 3);
  f32(edges, "edges", S + 1);
  f32(lo, "lo", 3);
  f32(cell, "cell", 3);
  TORCH_CHECK(res.scalar_type() == torch::kInt64 && res.numel() == 3, "march_occupied: res must be 3 int64");
  TORCH_CHECK(occupied.scalar_type() == torch::kBool && occupied.is_contiguous(), "march_occupied: occupied must be bool");
  TORCH_CHECK(first >= 0 && max_per_ray >= 0, "march_occupied: first and max_per_ray must be >= 0");
  const int64_t nx = res[0].item<int64_t>(), ny = res[1].item<int64_t>(), nz = res[2].item<int64_t>();
  TORCH_CHECK(occupied.numel() == nx * ny * nz, "march_occupied: occupied has ", occupied.numel(),
              " cells, res gives ", nx * ny * nz);
  const float* u = nullptr;
  if (u_opt.has_value() && u_opt->defined()) {
    f32(*u_opt, "u", R * S);
    u = u_opt->data_ptr<float>();
  }
  const float* tmax = nullptr;
  if (t_max_opt.has_value() && t_max_opt->defined()) {
    f32(*t_max_opt, "t_max", R);
    tmax = t_max_opt->data_ptr<float>();
  }
  const float* o = origins.data_ptr<float>();
  const float* d = dirs.data_ptr<float>();
  const float* e = edges.data_ptr<float>();
  const bool* occ = occupied.data_ptr<bool>();
  const float lo3[3] = {lo[0].item<float>(), lo[1].item<float>(), lo[2].item<float>()};
  const float cell3[3] = {cell[0].item<float>(), cell[1].item<float>(), cell[2].item<float>()};
  const int64_t last = max_per_ray > 0 ? first + max_per_ray : INT64_MAX;

  // Candidate c of ray r: its depth, and whether it is kept before ranking (occupied, before t_max).
  // floor(q) is never computed: for the bounds test floor(q) >= 0 iff q >= 0 and floor(q) < n iff q < n,
  // and inside the bounds the cell index floor(q) is the truncation (int64_t)q.
  const float n3[3] = {(float)nx, (float)ny, (float)nz};
  auto candidate = [&](int64_t r, int64_t c, float& t) -> bool {
    const float a = e[c], b = e[c + 1];
    t = a + (b - a) * (u ? u[r * S + c] : 0.5f);
    if (tmax && !(t <= tmax[r])) return false;
    int64_t ijk[3];
    for (int k = 0; k < 3; ++k) {
      const float q = (o[r * 3 + k] + d[r * 3 + k] * t - lo3[k]) / cell3[k];
      if (!(q >= 0.0f && q < n3[k])) return false;   // outside the bounds (or NaN)
      ijk[k] = (int64_t)q;
    }
    return occ[(ijk[0] * ny + ijk[1]) * nz + ijk[2]];
  };

  // One pass: each ray's kept samples go to its own scratch row (at most `cap`), then are packed.
  const int64_t cap = max_per_ray > 0 ? std::min<int64_t>(S, max_per_ray) : S;
  std::vector<int32_t> kept_col((size_t)(R * cap));
  std::vector<float> kept_t((size_t)(R * cap));
  std::vector<int64_t> count(R + 1, 0);
  at::parallel_for(0, R, 64, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      int64_t rank = 0, k = 0;
      int32_t* kc = kept_col.data() + r * cap;
      float* kt = kept_t.data() + r * cap;
      float t;
      for (int64_t c = 0; c < S && rank < last; ++c) {
        if (!candidate(r, c, t)) continue;
        if (rank >= first) {
          kc[k] = (int32_t)c;
          kt[k] = t;
          ++k;
        }
        ++rank;
      }
      count[r + 1] = k;
    }
  });
  for (int64_t r = 0; r < R; ++r) count[r + 1] += count[r];
  const int64_t K = count[R];
  auto ray_index = torch::empty({K}, torch::kInt64);
  auto col = torch::empty({K}, torch::kInt64);
  auto ts = torch::empty({K}, torch::kFloat32);
  int64_t* ri = ray_index.data_ptr<int64_t>();
  int64_t* ci = col.data_ptr<int64_t>();
  float* to = ts.data_ptr<float>();
  at::parallel_for(0, R, 256, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      const int64_t k0 = count[r], n = count[r + 1] - k0;
      for (int64_t j = 0; j < n; ++j) {
        ri[k0 + j] = r;
        ci[k0 + j] = kept_col[r * cap + j];
        to[k0 + j] = kept_t[r * cap + j];
      }
    }
  });
  return {ray_index, col, ts};
}
