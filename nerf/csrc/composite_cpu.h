// Fused volume compositing of packed samples (CPU, OpenMP over rays), included by permuto_cpu.cpp.
//
// The torch reference is nerf/render.py composite_weights() + accumulate(): per ray, tau_i = sigma_i delta_i
// (NaN, from inf * 0, counts as 0), T_i = exp(-sum_{j<i} tau_j), w_i = T_i (1 - exp(-tau_i)); the outputs are
// colour = sum w_i rgb_i [R, 3], depth = sum w_i t_i [R] and left = exp(-sum tau_i) [R]. The reference builds
// these from a dozen tensor ops (a dense scatter, a cumulative sum, gathers, index_add) and autograd keeps
// each op's inputs; here one pass per ray does the forward, and one pass per ray the backward.
//
// Backward, with v_i = g_colour . rgb_i + g_depth t_i (the output gradients of the sample's ray):
//   d/d rgb_i   = w_i g_colour
//   d/d tau_k   = v_k T_{k+1} - sum_{i>k} v_i w_i - g_left left
//   d/d sigma_k = d/d tau_k * delta_k  (0 where tau_k was NaN)
// where sum_{i>k} v_i w_i is the ray's whole sum (g_colour . colour + g_depth depth) less the running one.
//
// Inputs: sigma, delta, t [S] float32; rgb [S, 3] float32; ray_index [S] int64, non-decreasing, in [0, R).

// Start of each ray's run of samples: offsets [R + 1] (also used by ray_points_cpu.h).
static std::vector<int64_t> ray_offsets(const int64_t* ray, int64_t S, int64_t R) {
  std::vector<int64_t> off(R + 1, 0);
  for (int64_t i = 0; i < S; ++i) {
    TORCH_CHECK(ray[i] >= 0 && ray[i] < R, "packed samples: ray_index out of range");
    TORCH_CHECK(i == 0 || ray[i] >= ray[i - 1], "packed samples: ray_index must be non-decreasing");
    ++off[ray[i] + 1];
  }
  for (int64_t r = 0; r < R; ++r) off[r + 1] += off[r];
  return off;
}

static void composite_check(const torch::Tensor& sigma, const torch::Tensor& delta, const torch::Tensor& rgb,
                            const torch::Tensor& t, const torch::Tensor& ray_index) {
  const int64_t S = sigma.numel();
  for (const auto* x : {&sigma, &delta, &t}) {
    TORCH_CHECK(x->device().is_cpu() && x->scalar_type() == torch::kFloat32 && x->is_contiguous() &&
                x->numel() == S, "composite: sigma, delta and t must be contiguous CPU float32 [S]");
  }
  TORCH_CHECK(rgb.device().is_cpu() && rgb.scalar_type() == torch::kFloat32 && rgb.is_contiguous() &&
              rgb.dim() == 2 && rgb.size(0) == S && rgb.size(1) == 3,
              "composite: rgb must be contiguous float32 [S, 3]");
  TORCH_CHECK(ray_index.device().is_cpu() && ray_index.scalar_type() == torch::kInt64 && ray_index.is_contiguous() &&
              ray_index.numel() == S, "composite: ray_index must be contiguous int64 [S]");
}

static inline float optical_depth(float sigma, float delta) {
  const float tau = sigma * delta;
  return std::isnan(tau) ? 0.0f : tau;
}

// (colour [R, 3], depth [R], left [R])
std::vector<torch::Tensor> composite_forward(torch::Tensor sigma, torch::Tensor delta, torch::Tensor rgb,
                                             torch::Tensor t, torch::Tensor ray_index, int64_t n_rays) {
  composite_check(sigma, delta, rgb, t, ray_index);
  const int64_t S = sigma.numel(), R = n_rays;
  const auto off = ray_offsets(ray_index.data_ptr<int64_t>(), S, R);
  auto colour = torch::zeros({R, 3}, sigma.options());
  auto depth = torch::zeros({R}, sigma.options());
  auto left = torch::ones({R}, sigma.options());
  const float *sg = sigma.data_ptr<float>(), *dl = delta.data_ptr<float>(), *c = rgb.data_ptr<float>(),
              *tt = t.data_ptr<float>();
  float *oc = colour.data_ptr<float>(), *od = depth.data_ptr<float>(), *ol = left.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t r = 0; r < R; ++r) {
    float excl = 0.0f, c0 = 0.0f, c1 = 0.0f, c2 = 0.0f, d = 0.0f;
    for (int64_t i = off[r]; i < off[r + 1]; ++i) {
      const float tau = optical_depth(sg[i], dl[i]);
      const float w = std::exp(-excl) * (1.0f - std::exp(-tau));
      c0 += w * c[3 * i];
      c1 += w * c[3 * i + 1];
      c2 += w * c[3 * i + 2];
      d += w * tt[i];
      excl += tau;
    }
    oc[3 * r] = c0;
    oc[3 * r + 1] = c1;
    oc[3 * r + 2] = c2;
    od[r] = d;
    ol[r] = std::exp(-excl);
  }
  return {colour, depth, left};
}

// (grad_sigma [S], grad_rgb [S, 3]) from the outputs' gradients and the forward's inputs and outputs.
std::vector<torch::Tensor> composite_backward(torch::Tensor g_colour, torch::Tensor g_depth, torch::Tensor g_left,
                                              torch::Tensor sigma, torch::Tensor delta, torch::Tensor rgb,
                                              torch::Tensor t, torch::Tensor ray_index, torch::Tensor colour,
                                              torch::Tensor depth, torch::Tensor left) {
  composite_check(sigma, delta, rgb, t, ray_index);
  const int64_t S = sigma.numel(), R = colour.size(0);
  for (const auto* x : {&g_colour, &colour}) {
    TORCH_CHECK(x->scalar_type() == torch::kFloat32 && x->is_contiguous() && x->numel() == 3 * R,
                "composite_backward: colour and its gradient must be contiguous float32 [R, 3]");
  }
  for (const auto* x : {&g_depth, &g_left, &depth, &left}) {
    TORCH_CHECK(x->scalar_type() == torch::kFloat32 && x->is_contiguous() && x->numel() == R,
                "composite_backward: depth, left and their gradients must be contiguous float32 [R]");
  }
  const auto off = ray_offsets(ray_index.data_ptr<int64_t>(), S, R);
  auto g_sigma = torch::empty({S}, sigma.options());
  auto g_rgb = torch::empty({S, 3}, sigma.options());
  const float *sg = sigma.data_ptr<float>(), *dl = delta.data_ptr<float>(), *c = rgb.data_ptr<float>(),
              *tt = t.data_ptr<float>(), *gc = g_colour.data_ptr<float>(), *gd = g_depth.data_ptr<float>(),
              *gl = g_left.data_ptr<float>(), *oc = colour.data_ptr<float>(), *od = depth.data_ptr<float>(),
              *ol = left.data_ptr<float>();
  float *gs = g_sigma.data_ptr<float>(), *gr = g_rgb.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t r = 0; r < R; ++r) {
    const float a0 = gc[3 * r], a1 = gc[3 * r + 1], a2 = gc[3 * r + 2], ad = gd[r];
    const float total = a0 * oc[3 * r] + a1 * oc[3 * r + 1] + a2 * oc[3 * r + 2] + ad * od[r];
    const float tail = gl[r] * ol[r];
    float excl = 0.0f, done = 0.0f;
    for (int64_t i = off[r]; i < off[r + 1]; ++i) {
      const float tau_raw = sg[i] * dl[i];
      const float tau = std::isnan(tau_raw) ? 0.0f : tau_raw;
      const float w = std::exp(-excl) * (1.0f - std::exp(-tau));
      excl += tau;
      const float v = a0 * c[3 * i] + a1 * c[3 * i + 1] + a2 * c[3 * i + 2] + ad * tt[i];
      done += v * w;
      gr[3 * i] = w * a0;
      gr[3 * i + 1] = w * a1;
      gr[3 * i + 2] = w * a2;
      const float g_tau = v * std::exp(-excl) - (total - done) - tail;
      gs[i] = std::isnan(tau_raw) ? 0.0f : g_tau * dl[i];
    }
  }
  return {g_sigma, g_rgb};
}
