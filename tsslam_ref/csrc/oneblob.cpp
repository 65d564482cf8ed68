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
//
// Speed without changing a bit: the loops over the n + 1 edges of a coordinate have no branches
// (round and clamp are selects, the edge terms' neighbours come from padded arrays), so the
// compiler runs four or eight edges at a time in vector registers.  Each edge's value is computed
// by the same operations as one at a time: vector lanes round every add and multiply as the scalar
// instructions do, and nothing is fused or reordered (-ffp-contract=off, and FMA is never enabled).
// Co-SLAM's n = 16 has its own instance with the count known at compile time, and on x86-64
// processors with AVX2 a second copy of it compiled for 8-wide registers, chosen at run time.
// Measured against the one-edge-at-a-time loops before (22016 / 44032 points, 2 threads, medians of
// 40, alternating): codes 1.95 -> 0.51 / 3.86 -> 1.02 ms, gradient 2.55 -> 0.99 / 5.09 -> 1.94 ms;
// the portable copy alone 0.83 / 1.55 ms at 22016 points.
// Built with hash_grid.cpp into one extension by tsslam_ref/hash_kernel.py; tested against the
// PyTorch path and finite differences in tests/test_field.py, on both instruction sets.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <cmath>
#include <cstdint>
#include <vector>

#if defined(__GNUC__) && !defined(__clang__)
// For the functions below only (not the headers above, nor hash_grid.cpp, whose point-gradient
// loop ran 7 % slower with it): the compiler may evaluate both sides of a select, which it needs
// to run the edge loops in vector registers.  Values are unchanged (IEEE operations, same order);
// only floating-point exception flags, which nothing reads, could differ.  Clang does so by default.
#pragma GCC optimize("no-trapping-math")
#endif

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define TSSLAM_ONEBLOB_AVX2 1
#endif
#if defined(__GNUC__)
#define TSSLAM_ALWAYS_INLINE __attribute__((always_inline)) inline  // also into the AVX2 copies
#else
#define TSSLAM_ALWAYS_INLINE inline
#endif

namespace {

constexpr int64_t kPointGrain = 1024;
constexpr int kCoSLAMBins = 16;  // Co-SLAM's n_bins: the instance with a compile-time edge count

void check_points(const at::Tensor& points, int64_t n_bins) {
  TORCH_CHECK(points.device().is_cpu(), "oneblob: CPU tensors only");
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "oneblob: points must be (N, 3), got ", points.sizes());
  TORCH_CHECK(n_bins >= 2, "oneblob: n_bins must be >= 2, got ", n_bins);
}

// floor(x), equal to std::floor for every x: for |x| < 2^62 by truncation (one less where that
// rounded up), which needs no library call on processors without a round instruction.  The same
// truncation as hash_grid.cpp's floor_to_integer, which returns the integer corner and needs no
// guard (far points wrap there by design); here the floor stays a float and x is unbounded.
template <typename scalar_t>
TSSLAM_ALWAYS_INLINE scalar_t floor_value(scalar_t x) {
  const scalar_t limit = static_cast<scalar_t>(4611686018427387904.0);  // 2^62
  if (!(x > -limit && x < limit)) return std::floor(x);                  // also NaN
  const scalar_t truncated = static_cast<scalar_t>(static_cast<int64_t>(x));
  return truncated > x ? truncated - scalar_t(1) : truncated;
}

// The constants of both passes, in the points' dtype, and the bin edges b_j = j / n.
template <typename scalar_t>
struct Constants {
  scalar_t bins, zero = 0, one = 1, half = static_cast<scalar_t>(0.5), scale = static_cast<scalar_t>(0.9375);
  scalar_t c2 = static_cast<scalar_t>(2.0 / 3.0), c4 = static_cast<scalar_t>(0.2);
  std::vector<scalar_t> edges;
  explicit Constants(int64_t n_bins) : bins(static_cast<scalar_t>(n_bins)), edges(n_bins + 1) {
    for (int64_t j = 0; j <= n_bins; ++j) edges[j] = static_cast<scalar_t>(j) / bins;
  }
};

// Per-thread scratch of one coordinate's n + 1 edges: stack arrays when n is known at compile time.
template <typename scalar_t, int kBins>
struct Scratch {
  static constexpr int kSize = kBins > 0 ? kBins + 1 : 1;
  scalar_t fixed_a[kSize], fixed_b[kSize];
  std::vector<scalar_t> dynamic_a, dynamic_b;
  scalar_t *a, *b;
  explicit Scratch(int64_t n_bins) {
    if (kBins > 0) {
      a = fixed_a, b = fixed_b;
    } else {
      dynamic_a.resize(n_bins + 1), dynamic_b.resize(n_bins + 1);
      a = dynamic_a.data(), b = dynamic_b.data();
    }
  }
};

// r_j = round(d_j) and v_j = clamp(n e_j, -1, 1) of edge j, as selects.  d_j lies in (-1, 1], where
// round half to even (torch.round) is 1 above 1/2, -1 below -1/2 and 0 in between, ±1/2 included.
// w is n e_j before the clamp (the gradient's clamp mask needs it).
template <typename scalar_t>
TSSLAM_ALWAYS_INLINE void edge_offsets(scalar_t edge, scalar_t wrapped, const Constants<scalar_t>& k, scalar_t& r,
                                       scalar_t& w, scalar_t& v) {
  const scalar_t d = edge - wrapped;
  r = static_cast<scalar_t>(d > k.half) - static_cast<scalar_t>(d < -k.half);
  w = (d - r) * k.bins;
  const scalar_t lower = w < -k.one ? -k.one : w;  // std::max(w, -1)
  v = k.one < lower ? k.one : lower;                // std::min(lower, 1)
}

// One coordinate's n codes at target[0..n).  kBins > 0: n = kBins, fixed at compile time.
template <typename scalar_t, int kBins>
TSSLAM_ALWAYS_INLINE void encode_coordinate(scalar_t x, int64_t n_bins, const Constants<scalar_t>& k,
                                            Scratch<scalar_t, kBins>& scratch, scalar_t* target) {
  const int64_t n = kBins > 0 ? kBins : n_bins;
  const scalar_t wrapped = x - floor_value(x);
  scalar_t* cdf = scratch.a;
  for (int64_t j = 0; j <= n; ++j) {
    scalar_t r, w, v;
    edge_offsets(k.edges[j], wrapped, k, r, w, v);
    const scalar_t v2 = v * v;
    cdf[j] = k.scale * v * (k.one - v2 * k.c2 + v2 * v2 * k.c4) + k.half + r;
  }
  for (int64_t j = 0; j < n; ++j) target[j] = cdf[j + 1] - cdf[j];
}

// One coordinate's n + 1 edge terms gu_j n (see oneblob_backward) at target[0..n], from the
// gradient g[0..n) of its codes.
template <typename scalar_t, int kBins>
TSSLAM_ALWAYS_INLINE void coordinate_edge_terms(scalar_t x, const scalar_t* grad, int64_t n_bins,
                                                const Constants<scalar_t>& k, Scratch<scalar_t, kBins>& scratch,
                                                scalar_t* target) {
  const int64_t n = kBins > 0 ? kBins : n_bins;
  const scalar_t wrapped = x - floor_value(x);
  scalar_t* from_code_below = scratch.a;  // g_{j-1}, with g_{-1} = 0
  scalar_t* from_code_above = scratch.b;  // -g_j, with -g_n = 0
  from_code_below[0] = k.zero;
  for (int64_t j = 0; j < n; ++j) from_code_below[j + 1] = grad[j];
  for (int64_t j = 0; j < n; ++j) from_code_above[j] = -grad[j];
  from_code_above[n] = k.zero;
  for (int64_t j = 0; j <= n; ++j) {
    scalar_t r, w, v;
    edge_offsets(k.edges[j], wrapped, k, r, w, v);
    const scalar_t v2 = v * v;
    const scalar_t grad_a = from_code_below[j] + from_code_above[j];
    const scalar_t cubic = (k.one - v2 * k.c2) + (v2 * v2) * k.c4;  // C, as the forward rounds it
    const scalar_t grad_c = grad_a * (k.scale * v);
    const scalar_t quartic_term = (grad_c * k.c4) * v2;
    const scalar_t grad_v2 = (quartic_term + quartic_term) + (-grad_c) * k.c2;
    const scalar_t square_term = grad_v2 * v;
    const scalar_t grad_v = ((grad_a * cubic) * k.scale + square_term) + square_term;
    const bool inside = (w >= -k.one) & (w <= k.one);  // the clamp passes the gradient
    const scalar_t grad_w = inside ? grad_v : k.zero;
    target[j] = grad_w * k.bins;
  }
}

// Points [begin, end): codes (N, 3 n) or edge terms (N, 3, n + 1).
template <typename scalar_t, int kBins>
TSSLAM_ALWAYS_INLINE void encode_points(const scalar_t* points, int64_t begin, int64_t end, int64_t n_bins,
                                        const Constants<scalar_t>& k, scalar_t* codes) {
  Scratch<scalar_t, kBins> scratch(n_bins);
  for (int64_t p = begin; p < end; ++p) {
    for (int axis = 0; axis < 3; ++axis) {
      encode_coordinate<scalar_t, kBins>(points[3 * p + axis], n_bins, k, scratch, codes + (3 * p + axis) * n_bins);
    }
  }
}

template <typename scalar_t, int kBins>
TSSLAM_ALWAYS_INLINE void edge_terms_of_points(const scalar_t* points, const scalar_t* grad_codes, int64_t begin,
                                               int64_t end, int64_t n_bins, const Constants<scalar_t>& k,
                                               scalar_t* terms) {
  Scratch<scalar_t, kBins> scratch(n_bins);
  for (int64_t p = begin; p < end; ++p) {
    for (int axis = 0; axis < 3; ++axis) {
      coordinate_edge_terms<scalar_t, kBins>(points[3 * p + axis], grad_codes + (3 * p + axis) * n_bins, n_bins, k,
                                             scratch, terms + (3 * p + axis) * (n_bins + 1));
    }
  }
}

#ifdef TSSLAM_ONEBLOB_AVX2
// The n = 16 loops compiled for AVX2 (the same source inlined; no fused multiply-add: FMA is not
// enabled and -ffp-contract=off holds).
template <typename scalar_t>
__attribute__((target("avx2"))) void encode_points_avx2(const scalar_t* points, int64_t begin, int64_t end,
                                                        const Constants<scalar_t>& k, scalar_t* codes) {
  encode_points<scalar_t, kCoSLAMBins>(points, begin, end, kCoSLAMBins, k, codes);
}

template <typename scalar_t>
__attribute__((target("avx2"))) void edge_terms_of_points_avx2(const scalar_t* points, const scalar_t* grad_codes,
                                                               int64_t begin, int64_t end,
                                                               const Constants<scalar_t>& k, scalar_t* terms) {
  edge_terms_of_points<scalar_t, kCoSLAMBins>(points, grad_codes, begin, end, kCoSLAMBins, k, terms);
}
#endif

// Whether this processor runs the AVX2 copy (checked once).
bool avx2_available() {
#ifdef TSSLAM_ONEBLOB_AVX2
  static const bool available = __builtin_cpu_supports("avx2");
  return available;
#else
  return false;
#endif
}

// Which copy runs: 2 = AVX2 (n = 16 on a processor with it, when allowed), 1 = n = 16, 0 = any n.
int path(int64_t n_bins, bool allow_avx2) {
  if (n_bins != kCoSLAMBins) return 0;
  return allow_avx2 && avx2_available() ? 2 : 1;
}

}  // namespace

// (N, 3) points in box units -> (N, 3 n_bins) codes, dim-major (x bins, y bins, z bins).
// allow_avx2 = false runs the portable loops (tests compare both with the PyTorch path).
at::Tensor oneblob_forward(const at::Tensor& points_in, int64_t n_bins, bool allow_avx2) {
  check_points(points_in, n_bins);
  const auto points = points_in.contiguous();
  const int64_t n_points = points.size(0);
  auto codes = at::empty({n_points, 3 * n_bins}, points.options());
  const int which = path(n_bins, allow_avx2);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "oneblob_forward", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    scalar_t* out = codes.data_ptr<scalar_t>();
    const Constants<scalar_t> k(n_bins);
    at::parallel_for(0, n_points, kPointGrain, [&](int64_t begin, int64_t end) {
#ifdef TSSLAM_ONEBLOB_AVX2
      if (which == 2) return encode_points_avx2<scalar_t>(point_data, begin, end, k, out);
#endif
      if (which >= 1) return encode_points<scalar_t, kCoSLAMBins>(point_data, begin, end, n_bins, k, out);
      encode_points<scalar_t, 0>(point_data, begin, end, n_bins, k, out);
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
at::Tensor oneblob_backward(const at::Tensor& grad_codes_in, const at::Tensor& points_in, int64_t n_bins,
                            bool allow_avx2) {
  check_points(points_in, n_bins);
  const auto points = points_in.contiguous();
  const auto grad_codes = grad_codes_in.contiguous();
  const int64_t n_points = points.size(0);
  TORCH_CHECK(grad_codes.dim() == 2 && grad_codes.size(0) == n_points && grad_codes.size(1) == 3 * n_bins,
              "oneblob: grad_codes must be (N, 3 n_bins)");
  auto edge_terms = at::empty({n_points, 3, n_bins + 1}, points.options());
  const int which = path(n_bins, allow_avx2);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "oneblob_backward", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    const scalar_t* grad_data = grad_codes.data_ptr<scalar_t>();
    scalar_t* out = edge_terms.data_ptr<scalar_t>();
    const Constants<scalar_t> k(n_bins);
    at::parallel_for(0, n_points, kPointGrain, [&](int64_t begin, int64_t end) {
#ifdef TSSLAM_ONEBLOB_AVX2
      if (which == 2) return edge_terms_of_points_avx2<scalar_t>(point_data, grad_data, begin, end, k, out);
#endif
      if (which >= 1) {
        return edge_terms_of_points<scalar_t, kCoSLAMBins>(point_data, grad_data, begin, end, n_bins, k, out);
      }
      edge_terms_of_points<scalar_t, 0>(point_data, grad_data, begin, end, n_bins, k, out);
    });
  });
  return -edge_terms.sum(-1);
}

// Whether oneblob_forward / oneblob_backward with allow_avx2 = true run the AVX2 copy for n_bins = 16.
bool oneblob_uses_avx2() { return avx2_available(); }

TORCH_LIBRARY_FRAGMENT(tsslam_hash_grid, m) {
  m.def("oneblob_forward", &oneblob_forward);
  m.def("oneblob_backward", &oneblob_backward);
  m.def("oneblob_uses_avx2", &oneblob_uses_avx2);
}
