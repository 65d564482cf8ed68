// OneBlob encoding on the CPU: the codes and their gradient with respect to the points, one pass each.
//
// The compiled twin of OneBlobEncoding in tsslam_ref/field.py (TS-SLAM Sec. III-A, Co-SLAM's
// coordinate encoding; tcnn oneblob.h's quartic kernel).  For one coordinate x in box units and
// n bins, with the coordinate wrapped to w = x - floor(x) and the bin edges b_j = j / n, j = 0..n:
//
//     d_j = b_j - w,   r_j = round(d_j),   e_j = d_j - r_j        (e_j in [-1/2, 1/2])
//     v   = clamp(n e, -1, 1)
//     F(e)  = (15/16) v (1 - (2/3) v^2 + (1/5) v^4) + 1/2        (the kernel's CDF)
//     G_j   = F(e_j) + r_j
//     code_k = G_{k+1} - G_k,   k = 0..n-1
//
// Gradient (floor and round are constant almost everywhere, as in the PyTorch path):
//
//     d G_j / d x  = -F'(e_j),   F'(e) = n (15/16) (1 - v^2)^2 for |n e| <= 1, else 0
//     d x          = sum_k g_k (F'(e_k) - F'(e_{k+1}))
//
// Both passes round as the PyTorch path and its autograd gradient do: the same operations in the
// same order, constants in the points' dtype, so the compiled path gives the same numbers bit for
// bit (the gradient is evaluated through the chain rule of that path, not the closed form above).
// One thread per block of points; no state between the passes.
// Built with hash_grid.cpp into one extension by tsslam_ref/hash_kernel.py; tested against the
// PyTorch path and finite differences in tests/test_field.py.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <cmath>
#include <vector>

namespace {

constexpr int64_t kPointGrain = 1024;

void check_points(const at::Tensor& points, int64_t n_bins) {
  TORCH_CHECK(points.device().is_cpu(), "oneblob: CPU tensors only");
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "oneblob: points must be (N, 3), got ", points.sizes());
  TORCH_CHECK(n_bins >= 2, "oneblob: n_bins must be >= 2, got ", n_bins);
}

// e_j and r_j of one coordinate for j = 0..n_bins (the PyTorch path's roundings); edges[j] = j / n.
// d_j lies in (-1, 1], where round half to even (torch.round) is 1 above 1/2, -1 below -1/2 and 0
// in between, ±1/2 included: written as two comparisons instead of a call to nearbyint.
template <typename scalar_t>
inline void offsets(scalar_t x, const scalar_t* edges, int64_t n_bins, scalar_t* e, scalar_t* r) {
  const scalar_t wrapped = x - std::floor(x);
  const scalar_t half = static_cast<scalar_t>(0.5);
  for (int64_t j = 0; j <= n_bins; ++j) {
    const scalar_t d = edges[j] - wrapped;
    r[j] = d > half ? scalar_t(1) : (d < -half ? scalar_t(-1) : scalar_t(0));
    e[j] = d - r[j];
  }
}

template <typename scalar_t>
std::vector<scalar_t> bin_edges(int64_t n_bins) {
  std::vector<scalar_t> edges(n_bins + 1);
  for (int64_t j = 0; j <= n_bins; ++j) edges[j] = static_cast<scalar_t>(j) / static_cast<scalar_t>(n_bins);
  return edges;
}

}  // namespace

// (N, 3) points in box units -> (N, 3 n_bins) codes, dim-major (x bins, y bins, z bins).
at::Tensor oneblob_forward(const at::Tensor& points_in, int64_t n_bins) {
  check_points(points_in, n_bins);
  const auto points = points_in.contiguous();
  const int64_t n_points = points.size(0);
  auto codes = at::empty({n_points, 3 * n_bins}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "oneblob_forward", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    scalar_t* out = codes.data_ptr<scalar_t>();
    const scalar_t bins = static_cast<scalar_t>(n_bins);
    const scalar_t one = 1, half = static_cast<scalar_t>(0.5), scale = static_cast<scalar_t>(0.9375);
    const scalar_t c2 = static_cast<scalar_t>(2.0 / 3.0), c4 = static_cast<scalar_t>(0.2);
    at::parallel_for(0, n_points, kPointGrain, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> e(n_bins + 1), r(n_bins + 1), cdf(n_bins + 1);
      const std::vector<scalar_t> edges = bin_edges<scalar_t>(n_bins);
      for (int64_t n = begin; n < end; ++n) {
        for (int axis = 0; axis < 3; ++axis) {
          offsets(point_data[3 * n + axis], edges.data(), n_bins, e.data(), r.data());
          for (int64_t j = 0; j <= n_bins; ++j) {
            const scalar_t v = std::min(std::max(e[j] * bins, -one), one);
            const scalar_t v2 = v * v;
            cdf[j] = scale * v * (one - v2 * c2 + v2 * v2 * c4) + half + r[j];
          }
          scalar_t* target = out + n * 3 * n_bins + axis * n_bins;
          for (int64_t k = 0; k < n_bins; ++k) target[k] = cdf[k + 1] - cdf[k];
        }
      }
    });
  });
  return codes;
}

// d loss / d points (N, 3) from d loss / d codes (N, 3 n_bins), rounded as PyTorch's autograd rounds
// the gradient of the PyTorch path.  Per coordinate and edge j, with g the incoming gradient of
// one coordinate's n codes and v = clamp(w, -1, 1), w = n e_j (B = (15/16) v, C = 1 - (2/3) v^2 +
// (1/5) v^4, so that F = B C + 1/2):
//
//     gA_j  = g_{j-1} + (-g_j)                  (g_{-1} = g_n = 0: the two slices of the codes)
//     gv2   = ((gC 0.2) v2 + (gC 0.2) v2) + (-gC)(2/3),   gC = gA_j B     (v^4 = v2 v2, v^2 (2/3))
//     gv    = ((gA_j C) 0.9375 + gv2 v) + gv2 v                           (B = 0.9375 v, v2 = v v)
//     gu_j  = (|w| <= 1 ? gv : 0) n                                       (the clamp, v = clamp(u n))
//     d x   = -sum_j gu_j                     (the broadcast of the wrapped coordinate, summed by
//                                              at::sum over the n + 1 edges as autograd sums it)
//
// Each line is one of autograd's operations, each sum in the order its engine accumulates the
// gradients of a tensor used twice (tests/test_field.py checks bit equality).  The per-edge terms
// go to a (N, 3, n + 1) buffer and at::sum reduces it, because the order of that reduction is
// PyTorch's (it depends on the CPU's vector width).
at::Tensor oneblob_backward(const at::Tensor& grad_codes_in, const at::Tensor& points_in, int64_t n_bins) {
  check_points(points_in, n_bins);
  const auto points = points_in.contiguous();
  const auto grad_codes = grad_codes_in.contiguous();
  const int64_t n_points = points.size(0);
  TORCH_CHECK(grad_codes.dim() == 2 && grad_codes.size(0) == n_points && grad_codes.size(1) == 3 * n_bins,
              "oneblob: grad_codes must be (N, 3 n_bins)");
  auto edge_terms = at::empty({n_points, 3, n_bins + 1}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "oneblob_backward", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    const scalar_t* grad_data = grad_codes.data_ptr<scalar_t>();
    scalar_t* out = edge_terms.data_ptr<scalar_t>();
    const scalar_t bins = static_cast<scalar_t>(n_bins);
    const scalar_t zero = 0, one = 1, scale = static_cast<scalar_t>(0.9375);
    const scalar_t c2 = static_cast<scalar_t>(2.0 / 3.0), c4 = static_cast<scalar_t>(0.2);
    at::parallel_for(0, n_points, kPointGrain, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> e(n_bins + 1), r(n_bins + 1);
      const std::vector<scalar_t> edges = bin_edges<scalar_t>(n_bins);
      for (int64_t n = begin; n < end; ++n) {
        for (int axis = 0; axis < 3; ++axis) {
          offsets(point_data[3 * n + axis], edges.data(), n_bins, e.data(), r.data());
          const scalar_t* grad = grad_data + n * 3 * n_bins + axis * n_bins;
          scalar_t* target = out + (n * 3 + axis) * (n_bins + 1);
          for (int64_t j = 0; j <= n_bins; ++j) {
            const scalar_t w = e[j] * bins;
            const scalar_t v = std::min(std::max(w, -one), one);
            const scalar_t v2 = v * v;
            const scalar_t from_code_below = j > 0 ? grad[j - 1] : zero;
            const scalar_t from_code_above = j < n_bins ? -grad[j] : zero;
            const scalar_t grad_a = from_code_below + from_code_above;
            const scalar_t cubic = (one - v2 * c2) + (v2 * v2) * c4;  // C, as the forward rounds it
            const scalar_t grad_c = grad_a * (scale * v);
            const scalar_t quartic_term = (grad_c * c4) * v2;
            const scalar_t grad_v2 = (quartic_term + quartic_term) + (-grad_c) * c2;
            const scalar_t square_term = grad_v2 * v;
            const scalar_t grad_v = ((grad_a * cubic) * scale + square_term) + square_term;
            const scalar_t grad_w = (w >= -one && w <= one) ? grad_v : zero;
            target[j] = grad_w * bins;
          }
        }
      }
    });
  });
  return -edge_terms.sum(-1);
}

TORCH_LIBRARY_FRAGMENT(tsslam_hash_grid, m) {
  m.def("oneblob_forward", &oneblob_forward);
  m.def("oneblob_backward", &oneblob_backward);
}
