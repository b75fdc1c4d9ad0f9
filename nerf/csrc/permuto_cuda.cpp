// Torch binding of the CUDA encoding kernels (permuto_cuda_kernels.cu), with the same functions
// and signatures as the CPU module so nerf/encoding.py drives both alike. The CUDA forward makes
// no Jacobian (it returns None there); its backward recomputes the simplex and uses atomics.
#include <torch/extension.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>

#include <optional>
#include <vector>

const char* pag_cuda_forward(int kind, const float* x, const float* table, const int64_t* offsets, const float* coef,
                             const float* shifts, float* out, int64_t N, int64_t L, int64_t F, void* stream);
const char* pag_cuda_backward(int kind, const float* grad_out, const float* x, const float* table,
                              const int64_t* offsets, const float* coef, const float* shifts, float* gtable,
                              float* gx, int64_t N, int64_t L, int64_t F, void* stream);

namespace {

// The table is flat, [R, F]: level l's rows are offsets[l] .. offsets[l + 1], a power of two of them (the
// offsets come as a CPU tensor, checked here, and go to the kernels on the device).
torch::Tensor check(const torch::Tensor& x, const torch::Tensor& table, const torch::Tensor& offsets,
                    const torch::Tensor& coef, const torch::Tensor& shifts) {
  for (const auto* t : {&x, &table, &coef, &shifts}) {
    TORCH_CHECK(t->is_cuda() && t->scalar_type() == torch::kFloat32, "all inputs must be CUDA float32 tensors");
    TORCH_CHECK(t->device() == x.device(), "all inputs must be on ", x.device());
  }
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, "x must be [N, 3], got ", x.sizes());
  TORCH_CHECK(table.dim() == 2, "table must be [R, F], got ", table.sizes());
  TORCH_CHECK(coef.dim() == 2 && coef.size(1) == 3, "coef must be [L, 3]");
  const int64_t L = coef.size(0);
  TORCH_CHECK(shifts.dim() == 2 && shifts.size(0) == L && shifts.size(1) == 3, "shifts must be [L, 3]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && offsets.dim() == 1 && offsets.size(0) == L + 1,
              "offsets must be int64 [L + 1]");
  const auto o = offsets.to(torch::kCPU).contiguous();
  const int64_t* off = o.data_ptr<int64_t>();
  TORCH_CHECK(off[0] == 0 && off[L] == table.size(0), "offsets must run from 0 to the table's rows");
  for (int64_t l = 0; l < L; ++l) {
    const int64_t T = off[l + 1] - off[l];
    TORCH_CHECK(T > 0 && (T & (T - 1)) == 0 && T * table.size(1) < (int64_t(1) << 32),
                "each level's rows must be a power of two with rows * F < 2^32, got ", T, " at level ", l);
  }
  return o.to(x.device());
}

std::vector<torch::Tensor> forward(int kind, torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                   torch::Tensor coef, torch::Tensor shifts) {
  const c10::cuda::CUDAGuard guard(x.device());
  const torch::Tensor off = check(x, table, offsets, coef, shifts);
  x = x.contiguous(); table = table.contiguous(); coef = coef.contiguous(); shifts = shifts.contiguous();
  const int64_t N = x.size(0), L = coef.size(0), F = table.size(1);
  auto out = torch::empty({N, L * F}, x.options());
  const char* err = pag_cuda_forward(kind, x.data_ptr<float>(), table.data_ptr<float>(), off.data_ptr<int64_t>(),
                                     coef.data_ptr<float>(), shifts.data_ptr<float>(), out.data_ptr<float>(), N, L, F,
                                     at::cuda::getCurrentCUDAStream().stream());
  TORCH_CHECK(err == nullptr, "encoding forward kernel failed: ", err ? err : "");
  return {out, torch::Tensor()};
}

std::vector<torch::Tensor> backward(int kind, torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                    torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts, bool need_table,
                                    bool need_x) {
  const c10::cuda::CUDAGuard guard(x.device());
  const torch::Tensor off = check(x, table, offsets, coef, shifts);
  x = x.contiguous(); table = table.contiguous(); coef = coef.contiguous(); shifts = shifts.contiguous();
  grad_out = grad_out.contiguous();
  const int64_t N = x.size(0), L = coef.size(0), F = table.size(1);
  TORCH_CHECK(grad_out.is_cuda() && grad_out.scalar_type() == torch::kFloat32 && grad_out.dim() == 2 &&
                  grad_out.size(0) == N && grad_out.size(1) == L * F, "grad_out must be CUDA float32 [N, L * F]");
  auto gtable = need_table ? torch::zeros_like(table) : torch::Tensor();
  auto gx = need_x ? torch::zeros_like(x) : torch::Tensor();
  const char* err = pag_cuda_backward(kind, grad_out.data_ptr<float>(), x.data_ptr<float>(), table.data_ptr<float>(),
                                      off.data_ptr<int64_t>(), coef.data_ptr<float>(), shifts.data_ptr<float>(),
                                      need_table ? gtable.data_ptr<float>() : nullptr,
                                      need_x ? gx.data_ptr<float>() : nullptr, N, L, F,
                                      at::cuda::getCurrentCUDAStream().stream());
  TORCH_CHECK(err == nullptr, "encoding backward kernel failed: ", err ? err : "");
  return {gtable, gx};
}

}  // namespace

std::vector<torch::Tensor> permuto_forward(torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                           torch::Tensor coef, torch::Tensor shifts, bool /*need_jac*/) {
  return forward(0, x, table, offsets, coef, shifts);
}

std::vector<torch::Tensor> permuto_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                            torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts,
                                            std::optional<torch::Tensor> /*jac*/, bool need_table, bool need_x) {
  return backward(0, grad_out, x, table, offsets, coef, shifts, need_table, need_x);
}

std::vector<torch::Tensor> cubic_forward(torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                         torch::Tensor coef, torch::Tensor shifts, bool /*need_jac*/) {
  return forward(1, x, table, offsets, coef, shifts);
}

std::vector<torch::Tensor> cubic_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor table,
                                          torch::Tensor offsets, torch::Tensor coef, torch::Tensor shifts,
                                          std::optional<torch::Tensor> /*jac*/, bool need_table, bool need_x) {
  return backward(1, grad_out, x, table, offsets, coef, shifts, need_table, need_x);
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("permuto_forward", &permuto_forward, "permutohedral hash encoding forward (CUDA): (features, None)");
  m.def("permuto_backward", &permuto_backward, "permutohedral hash encoding backward (CUDA): (grad_table, grad_x)");
  m.def("cubic_forward", &cubic_forward, "cubic hash grid forward (CUDA): (features, None)");
  m.def("cubic_backward", &cubic_backward, "cubic hash grid backward (CUDA): (grad_table, grad_x)");
}
