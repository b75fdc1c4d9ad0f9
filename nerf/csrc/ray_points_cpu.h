// Sample points of packed samples and their unit directions (CPU, OpenMP over rays), included by
// permuto_cpu.cpp. The torch reference is nerf/model.py NerfModel.shade(): x_i = o_r + d_r t_i and
// dn_i = d_r / |d_r| for sample i of ray r, two gathers, a product and a normalisation, whose backward
// scatters the gradients back into the rays with index_put. Here the samples of a ray are one run
// (ray_index non-decreasing), so the backward sums each run in place:
//   d/d o_r = sum_i g_x_i,   d/d d_r = sum_i g_x_i t_i + (G - dn_r (dn_r . G)) / |d_r|,  G = sum_i g_dn_i.
// Inputs: o, d [R, 3] float32; t [S] float32; ray_index [S] int64 in [0, R), non-decreasing.

static void ray_points_check(const torch::Tensor& o, const torch::Tensor& d, const torch::Tensor& t,
                             const torch::Tensor& ray_index) {
  const int64_t R = o.size(0), S = t.numel();
  for (const auto* x : {&o, &d}) {
    TORCH_CHECK(x->device().is_cpu() && x->scalar_type() == torch::kFloat32 && x->is_contiguous() && x->dim() == 2 &&
                x->size(0) == R && x->size(1) == 3, "ray_points: o and d must be contiguous CPU float32 [R, 3]");
  }
  TORCH_CHECK(t.scalar_type() == torch::kFloat32 && t.is_contiguous(), "ray_points: t must be contiguous float32 [S]");
  TORCH_CHECK(ray_index.scalar_type() == torch::kInt64 && ray_index.is_contiguous() && ray_index.numel() == S,
              "ray_points: ray_index must be contiguous int64 [S]");
}

// (x [S, 3], dn [S, 3]); with_dirs false: dn is empty.
std::vector<torch::Tensor> ray_points_forward(torch::Tensor o, torch::Tensor d, torch::Tensor t,
                                              torch::Tensor ray_index, bool with_dirs) {
  ray_points_check(o, d, t, ray_index);
  const int64_t R = o.size(0), S = t.numel();
  const auto off = ray_offsets(ray_index.data_ptr<int64_t>(), S, R);
  auto x = torch::empty({S, 3}, o.options());
  auto dn = torch::empty({with_dirs ? S : 0, 3}, o.options());
  const float *po = o.data_ptr<float>(), *pd = d.data_ptr<float>(), *pt = t.data_ptr<float>();
  float *px = x.data_ptr<float>(), *pn = dn.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t r = 0; r < R; ++r) {
    const float o0 = po[3 * r], o1 = po[3 * r + 1], o2 = po[3 * r + 2];
    const float d0 = pd[3 * r], d1 = pd[3 * r + 1], d2 = pd[3 * r + 2];
    const float inv = 1.0f / std::max(std::sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-12f);
    for (int64_t i = off[r]; i < off[r + 1]; ++i) {
      px[3 * i] = o0 + d0 * pt[i];
      px[3 * i + 1] = o1 + d1 * pt[i];
      px[3 * i + 2] = o2 + d2 * pt[i];
      if (with_dirs) {
        pn[3 * i] = d0 * inv;
        pn[3 * i + 1] = d1 * inv;
        pn[3 * i + 2] = d2 * inv;
      }
    }
  }
  return {x, dn};
}

// (grad_o [R, 3], grad_d [R, 3]); g_dn undefined: no direction gradient.
std::vector<torch::Tensor> ray_points_backward(torch::Tensor g_x, c10::optional<torch::Tensor> g_dn_opt,
                                               torch::Tensor o, torch::Tensor d, torch::Tensor t,
                                               torch::Tensor ray_index) {
  ray_points_check(o, d, t, ray_index);
  const int64_t R = o.size(0), S = t.numel();
  TORCH_CHECK(g_x.scalar_type() == torch::kFloat32 && g_x.is_contiguous() && g_x.numel() == 3 * S,
              "ray_points_backward: g_x must be contiguous float32 [S, 3]");
  const float* gn = nullptr;
  if (g_dn_opt.has_value() && g_dn_opt->defined()) {
    TORCH_CHECK(g_dn_opt->scalar_type() == torch::kFloat32 && g_dn_opt->is_contiguous() && g_dn_opt->numel() == 3 * S,
                "ray_points_backward: g_dn must be contiguous float32 [S, 3]");
    gn = g_dn_opt->data_ptr<float>();
  }
  const auto off = ray_offsets(ray_index.data_ptr<int64_t>(), S, R);
  auto g_o = torch::empty({R, 3}, o.options());
  auto g_d = torch::empty({R, 3}, o.options());
  const float *pd = d.data_ptr<float>(), *pt = t.data_ptr<float>(), *gx = g_x.data_ptr<float>();
  float *go = g_o.data_ptr<float>(), *gd = g_d.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t r = 0; r < R; ++r) {
    float so[3] = {0.0f, 0.0f, 0.0f}, sd[3] = {0.0f, 0.0f, 0.0f}, sn[3] = {0.0f, 0.0f, 0.0f};
    for (int64_t i = off[r]; i < off[r + 1]; ++i) {
      for (int k = 0; k < 3; ++k) {
        so[k] += gx[3 * i + k];
        sd[k] += gx[3 * i + k] * pt[i];
        if (gn) sn[k] += gn[3 * i + k];
      }
    }
    const float d0 = pd[3 * r], d1 = pd[3 * r + 1], d2 = pd[3 * r + 2];
    const float norm = std::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    if (gn && norm > 1e-12f) {
      const float n3[3] = {d0 / norm, d1 / norm, d2 / norm};
      const float dot = n3[0] * sn[0] + n3[1] * sn[1] + n3[2] * sn[2];
      for (int k = 0; k < 3; ++k) sd[k] += (sn[k] - n3[k] * dot) / norm;
    } else if (gn) {
      for (int k = 0; k < 3; ++k) sd[k] += sn[k] / 1e-12f;
    }
    for (int k = 0; k < 3; ++k) {
      go[3 * r + k] = so[k];
      gd[3 * r + k] = sd[k];
    }
  }
  return {g_o, g_d};
}
