// Multi-resolution hash-grid lookup on the CPU: hash + gather + trilinear interpolation in one pass.
//
// The compiled twin of HashGridEncoding._encode_fast in tsslam_ref/field.py (TS-SLAM Sec. III-A,
// Co-SLAM's parametric encoding V(x); tiny-cuda-nn grid.h level geometry).
// Built on first use by tsslam_ref/hash_kernel.py with torch.utils.cpp_extension; tested against
// the PyTorch paths and finite differences in tests/test_field.py.
//
// For level l with scale s_l, R_l vertices per axis, table rows [offset_l, offset_l + size_l):
//
//     p        = x_n * s_l + 0.5,  corner = floor(p),  f = p - corner
//     row(c)   = offset_l + (i + j R + k R^2 mod 2^32) mod size_l            dense levels
//                offset_l + ((i * 1) ^ (j * 2654435761) ^ (k * 805459861)) mod size_l   hashed
//     out[l]   = sum_c w_c(f) table[row(c)],   w_c = prod_axis (f or 1 - f),  corner order dx, dy, dz
//
// Backward:
//     d table[row(c)]  += w_c * g[l]                   (one thread owns each level: no races, and the
//                                                       sum runs in point order: deterministic)
//     d x_n            += s_l * sum_c (d w_c / d f) <table[row(c)], g[l]>   (one thread per point,
//                                                       levels in order)
// When both are wanted (BA) one pass over the levels does both, keeping each level's point term
// and summing the terms over levels in order afterwards (the same numbers, one locate per point).
//
// Features and their gradients are point-major, (N, L, F), the layout of the MLP's input (N, L F),
// so no copy stands between the kernel and the MLP either way; the loops over points run level by
// level inside blocks of points, whose rows of features stay in cache meanwhile.  The table
// gradient, which runs one level at a time over all points, reads its level's F values of each
// point's row in place (a constant stride the prefetcher follows; copying the gradient to
// level-major (L, N, F) first cost more than the strided reads: 8.1 -> 6.8 ms at 44032 points).
//
// Speed without changing a bit: each point-and-level branches once between the dense and the hashed
// index (not once per corner), and F = 2 (Co-SLAM's features per level) has its own unrolled
// feature loops; every sum keeps its order, so all three paths give the numbers of the general loop.
//
// Nothing is stored between forward and backward but the inputs: the rows and weights are
// recomputed, which is cheaper on two cores than writing and re-reading an (8, L, N) index.
// Compile with -fopenmp (at::parallel_for runs on OpenMP threads; without it every loop is serial)
// and -ffp-contract=off (every product and sum rounds as the PyTorch path does).

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;

// One level's geometry, read once per call: the loops over points hold it in registers instead
// of re-reading (and re-deriving) it for every point.
struct Level {
  double scale;
  int64_t offset;      // first table row of the level
  uint64_t size;       // rows of the level
  uint32_t resolution;  // vertices per axis (dense index)
  bool dense;
  bool power_of_two;   // size = 2^k: "mod size" is a mask
};

std::vector<Level> read_levels(const at::Tensor& scales, const at::Tensor& resolutions, const at::Tensor& sizes,
                               const at::Tensor& offsets, int64_t n_dense) {
  TORCH_CHECK(scales.dim() == 1 && resolutions.dim() == 1 && sizes.dim() == 1 && offsets.dim() == 1,
              "hash_grid: level tensors must be 1-D");
  const int64_t count = scales.size(0);
  TORCH_CHECK(resolutions.size(0) == count && sizes.size(0) == count && offsets.size(0) == count,
              "hash_grid: level tensors must have the same length");
  const auto scale = scales.to(at::kDouble).contiguous();
  const auto resolution = resolutions.to(at::kLong).contiguous();
  const auto size = sizes.to(at::kLong).contiguous();
  const auto offset = offsets.to(at::kLong).contiguous();
  std::vector<Level> levels;
  for (int64_t l = 0; l < count; ++l) {
    const int64_t level_size = size.data_ptr<int64_t>()[l];
    TORCH_CHECK(level_size > 0 && level_size <= (int64_t(1) << 32), "hash_grid: level size out of range");
    levels.push_back(Level{scale.data_ptr<double>()[l], offset.data_ptr<int64_t>()[l],
                           static_cast<uint64_t>(level_size),
                           static_cast<uint32_t>(resolution.data_ptr<int64_t>()[l]), l < n_dense,
                           (level_size & (level_size - 1)) == 0});
  }
  return levels;
}

// The 8 corner rows and trilinear weights of one point on one level, corner order dx, dy, dz.
template <typename scalar_t>
struct Cell {
  int64_t row[8];
  scalar_t weight[8];
  scalar_t fraction[3];
};

// cell.row[c] for the 8 corners from index(i, j, k), the level's dense or hashed index.
template <typename scalar_t, typename Index>
inline void corner_rows(const uint32_t corner[3], const Level& level, const Index& index, Cell<scalar_t>& cell) {
  int c = 0;
  for (uint32_t dx = 0; dx < 2; ++dx) {
    for (uint32_t dy = 0; dy < 2; ++dy) {
      for (uint32_t dz = 0; dz < 2; ++dz, ++c) {
        const uint64_t local = index(corner[0] + dx, corner[1] + dy, corner[2] + dz);
        // mod size: a mask for the 2^T hashed tables, a division only for a dense index past the
        // table (points outside the box); divisions would dominate the loop otherwise
        const uint64_t wrapped =
            level.power_of_two ? (local & (level.size - 1)) : (local < level.size ? local : local % level.size);
        cell.row[c] = level.offset + static_cast<int64_t>(wrapped);
      }
    }
  }
}

// floor(x) as an integer, for |x| < 2^63: the truncation toward zero, one less where that rounded
// up (x < 0 with a fraction).  Equal to std::floor(x) for every such x (a float of magnitude 2^23 or
// more is an integer already), but two conversions and a compare: without SSE4.1's round
// instruction, which a plain x86-64 build may not use, std::floor is a library call, and it ran
// once per point, level and axis.
template <typename scalar_t>
inline int64_t floor_to_integer(scalar_t x) {
  const int64_t truncated = static_cast<int64_t>(x);
  return static_cast<scalar_t>(truncated) > x ? truncated - 1 : truncated;
}

template <typename scalar_t>
inline void locate(const scalar_t* point, const Level& level, Cell<scalar_t>& cell) {
  const scalar_t scale = static_cast<scalar_t>(level.scale);
  const scalar_t half = static_cast<scalar_t>(0.5);
  uint32_t corner[3];
  for (int axis = 0; axis < 3; ++axis) {
    const scalar_t position = point[axis] * scale + half;
    const int64_t floored = floor_to_integer(position);
    cell.fraction[axis] = position - static_cast<scalar_t>(floored);
    corner[axis] = static_cast<uint32_t>(floored);  // two's complement wrap
  }
  const uint32_t resolution = level.resolution;
  const scalar_t one = static_cast<scalar_t>(1);
  const scalar_t wx[2] = {one - cell.fraction[0], cell.fraction[0]};
  const scalar_t wy[2] = {one - cell.fraction[1], cell.fraction[1]};
  const scalar_t wz[2] = {one - cell.fraction[2], cell.fraction[2]};
  // One well-predicted branch per point and level (a level's points all take the same side);
  // each corner loop is then straight-line code.
  if (level.dense) {
    corner_rows(corner, level, [resolution](uint32_t i, uint32_t j, uint32_t k) -> uint64_t {
      return i + (j + k * resolution) * resolution;
    }, cell);
  } else {
    corner_rows(corner, level, [](uint32_t i, uint32_t j, uint32_t k) -> uint64_t {
      return i ^ (j * kPrimeY) ^ (k * kPrimeZ);
    }, cell);
  }
  int c = 0;
  for (int dx = 0; dx < 2; ++dx) {
    for (int dy = 0; dy < 2; ++dy) {
      const scalar_t wxy = wx[dx] * wy[dy];
      for (int dz = 0; dz < 2; ++dz, ++c) cell.weight[c] = wxy * wz[dz];
    }
  }
}

void check_inputs(const at::Tensor& points, const at::Tensor& table) {
  TORCH_CHECK(points.device().is_cpu() && table.device().is_cpu(), "hash_grid: CPU tensors only");
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "hash_grid: points must be (N, 3), got ", points.sizes());
  TORCH_CHECK(table.dim() == 2, "hash_grid: table must be (T, F), got ", table.sizes());
  TORCH_CHECK(points.scalar_type() == table.scalar_type(), "hash_grid: points and table must share a dtype");
}

// Points per block of the point loops, at most.  Inside a block the loops run level by level, so
// the random reads and writes of one level stay in one table of at most 2^T rows (512 KiB at
// T = 16, float32, F = 2), which fits the core's L2 cache, instead of hopping over all L tables per
// point.  Larger blocks read each level's table into cache fewer times; measured on 22016
// tracking points and on 44032 random ones (2 threads), forward and point gradient ran 7-14 %
// faster with 16384-point blocks than with 2048 (1024 to 16384 tried, each step faster).  No
// result depends on the block size.
constexpr int64_t kBlock = 16384;

// Points per thread, at least, of the one-pass backward's final sum over levels (a plain stream).
constexpr int64_t kSumGrain = 2048;

// Runs body(begin, end) over blocks of at most kBlock points, blocks split among threads.  The
// number of blocks is a multiple of the thread count and the blocks are of equal size (to one
// point), so every thread gets the same number of points: with fixed 2048-point blocks the 22016
// points of a tracking iteration made 11 blocks, 6 on one thread and 5 (one partial) on the other
// (with 16384-point blocks they make 2 of 11008).
// Each point's result does not depend on the blocking.
template <typename Body>
void for_point_blocks(int64_t n_points, const Body& body) {
  if (n_points == 0) return;
  const int64_t threads = std::max<int64_t>(1, at::get_num_threads());
  int64_t n_blocks = (n_points + kBlock - 1) / kBlock;
  n_blocks = std::min(n_points, (n_blocks + threads - 1) / threads * threads);
  const int64_t block_size = (n_points + n_blocks - 1) / n_blocks;
  n_blocks = (n_points + block_size - 1) / block_size;
  at::parallel_for(0, n_blocks, 1, [&](int64_t first, int64_t last) {
    for (int64_t block = first; block < last; ++block) {
      body(block * block_size, std::min(n_points, (block + 1) * block_size));
    }
  });
}

void check_grad(const at::Tensor& grad_features, int64_t n_levels, int64_t n_points, int64_t n_features) {
  TORCH_CHECK(grad_features.dim() == 3 && grad_features.size(0) == n_points && grad_features.size(1) == n_levels &&
                  grad_features.size(2) == n_features,
              "hash_grid: grad_features must be (N, L, F) = (", n_points, ", ", n_levels, ", ", n_features, "), got ",
              grad_features.sizes());
}

// A backward op's inputs, checked and made contiguous once: grad_features (N, L, F), points (N, 3),
// table (T, F) and the level geometry.
struct BackwardInputs {
  at::Tensor grad_features, points, table;
  std::vector<Level> levels;
  int64_t n_points, n_features, n_levels;
};

BackwardInputs backward_inputs(const at::Tensor& grad_features, const at::Tensor& points, const at::Tensor& table,
                               const at::Tensor& scales, const at::Tensor& resolutions, const at::Tensor& sizes,
                               const at::Tensor& offsets, int64_t n_dense) {
  check_inputs(points, table);
  BackwardInputs inputs{grad_features.contiguous(), points.contiguous(), table.contiguous(),
                        read_levels(scales, resolutions, sizes, offsets, n_dense), points.size(0), table.size(1), 0};
  inputs.n_levels = static_cast<int64_t>(inputs.levels.size());
  check_grad(inputs.grad_features, inputs.n_levels, inputs.n_points, inputs.n_features);
  return inputs;
}

}  // namespace

// (N, 3) points in box units, (T, F) table -> (N, L, F) features.
at::Tensor hash_grid_forward(const at::Tensor& points_in, const at::Tensor& table_in, const at::Tensor& scales,
                             const at::Tensor& resolutions, const at::Tensor& sizes, const at::Tensor& offsets,
                             int64_t n_dense) {
  check_inputs(points_in, table_in);
  const auto points = points_in.contiguous();
  const auto table = table_in.contiguous();
  const std::vector<Level> levels = read_levels(scales, resolutions, sizes, offsets, n_dense);
  const int64_t n_points = points.size(0), n_features = table.size(1), n_levels = static_cast<int64_t>(levels.size());
  auto features = at::empty({n_points, n_levels, n_features}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hash_grid_forward", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    const scalar_t* table_data = table.data_ptr<scalar_t>();
    scalar_t* out = features.data_ptr<scalar_t>();
    for_point_blocks(n_points, [&](int64_t begin, int64_t end) {
      Cell<scalar_t> cell;
      for (int64_t l = 0; l < n_levels; ++l) {
        const Level level = levels[l];
        for (int64_t n = begin; n < end; ++n) {
          locate(point_data + 3 * n, level, cell);
          scalar_t* target = out + (n * n_levels + l) * n_features;
          if (n_features == 2) {  // Co-SLAM's F: a loop the compiler unrolls, the same sums
            for (int f = 0; f < 2; ++f) {
              scalar_t sum = cell.weight[0] * table_data[cell.row[0] * 2 + f];
              for (int c = 1; c < 8; ++c) sum = sum + cell.weight[c] * table_data[cell.row[c] * 2 + f];
              target[f] = sum;
            }
            continue;
          }
          for (int64_t f = 0; f < n_features; ++f) {
            scalar_t sum = cell.weight[0] * table_data[cell.row[0] * n_features + f];
            for (int c = 1; c < 8; ++c) sum = sum + cell.weight[c] * table_data[cell.row[c] * n_features + f];
            target[f] = sum;
          }
        }
      }
    });
  });
  return features;
}

// d table[row(c)] += w_c * g for the 8 corners of one point on one level.
template <typename scalar_t>
inline void add_table_gradient(const Cell<scalar_t>& cell, const scalar_t* grad, int64_t n_features,
                               scalar_t* grad_table_data) {
  if (n_features == 2) {  // Co-SLAM's F, unrolled: the same sums
    for (int c = 0; c < 8; ++c) {
      scalar_t* row = grad_table_data + cell.row[c] * 2;
      row[0] += cell.weight[c] * grad[0];
      row[1] += cell.weight[c] * grad[1];
    }
    return;
  }
  for (int c = 0; c < 8; ++c) {
    scalar_t* row = grad_table_data + cell.row[c] * n_features;
    for (int64_t f = 0; f < n_features; ++f) row[f] += cell.weight[c] * grad[f];
  }
}

// One level's term of d loss / d x_n, written to term[3]: s_l sum_c (d w_c / d f) <table[row(c)], g>.
template <typename scalar_t>
inline void point_gradient_term(const Cell<scalar_t>& cell, const scalar_t* table_data, const scalar_t* grad,
                                int64_t n_features, scalar_t scale, scalar_t term[3]) {
  scalar_t grad_weight[8];  // d loss / d w_c = <table[row(c)], g>
  if (n_features == 2) {  // Co-SLAM's F, unrolled: the same sums
    for (int c = 0; c < 8; ++c) {
      scalar_t dot = 0;
      dot += table_data[cell.row[c] * 2] * grad[0];
      dot += table_data[cell.row[c] * 2 + 1] * grad[1];
      grad_weight[c] = dot;
    }
  } else {
    for (int c = 0; c < 8; ++c) {
      scalar_t dot = 0;
      for (int64_t f = 0; f < n_features; ++f) dot += table_data[cell.row[c] * n_features + f] * grad[f];
      grad_weight[c] = dot;
    }
  }
  const scalar_t one = static_cast<scalar_t>(1);
  const scalar_t wx[2] = {one - cell.fraction[0], cell.fraction[0]};
  const scalar_t wy[2] = {one - cell.fraction[1], cell.fraction[1]};
  const scalar_t wz[2] = {one - cell.fraction[2], cell.fraction[2]};
  scalar_t gx = 0, gy = 0, gz = 0;
  for (int a = 0; a < 2; ++a) {
    for (int b = 0; b < 2; ++b) {
      // corner index c = 4 dx + 2 dy + dz
      gx += (grad_weight[4 + 2 * a + b] - grad_weight[2 * a + b]) * wy[a] * wz[b];
      gy += (grad_weight[4 * a + 2 + b] - grad_weight[4 * a + b]) * wx[a] * wz[b];
      gz += (grad_weight[4 * a + 2 * b + 1] - grad_weight[4 * a + 2 * b]) * wx[a] * wy[b];
    }
  }
  term[0] = gx * scale;
  term[1] = gy * scale;
  term[2] = gz * scale;
}

// The table gradient from point-major (N, L, F) gradients, levels split among threads in an
// interleaved order (dense, cache-friendly levels and hashed ones mixed), each level summed by one
// thread in point order.  With point_terms (L, N, 3) it also writes each level's term of the point
// gradient there, from the same located cell: the caller sums them over levels in order
// (hash_grid_backward).
template <typename scalar_t>
void table_gradient_by_level(const scalar_t* point_data, const scalar_t* table_data, const scalar_t* grad_data,
                             const std::vector<Level>& levels, int64_t n_points, int64_t n_features,
                             scalar_t* grad_table_data, scalar_t* point_terms) {
  const int64_t n_levels = static_cast<int64_t>(levels.size());
  std::vector<int64_t> level_order;
  for (int64_t l = 0; l < n_levels; l += 2) level_order.push_back(l);
  for (int64_t l = 1; l < n_levels; l += 2) level_order.push_back(l);
  at::parallel_for(0, n_levels, 1, [&](int64_t begin, int64_t end) {
    Cell<scalar_t> cell;
    for (int64_t position = begin; position < end; ++position) {
      const int64_t l = level_order[position];
      const Level level = levels[l];
      const scalar_t scale = static_cast<scalar_t>(level.scale);
      for (int64_t n = 0; n < n_points; ++n) {
        locate(point_data + 3 * n, level, cell);
        const scalar_t* grad = grad_data + (n * n_levels + l) * n_features;
        add_table_gradient(cell, grad, n_features, grad_table_data);
        if (point_terms != nullptr) {
          point_gradient_term(cell, table_data, grad, n_features, scale, point_terms + (l * n_points + n) * 3);
        }
      }
    }
  });
}

// d loss / d table, (T, F), from (N, L, F) output gradients.
at::Tensor hash_grid_backward_table(const at::Tensor& grad_features_in, const at::Tensor& points_in,
                                    const at::Tensor& table, const at::Tensor& scales, const at::Tensor& resolutions,
                                    const at::Tensor& sizes, const at::Tensor& offsets, int64_t n_dense) {
  const BackwardInputs in = backward_inputs(grad_features_in, points_in, table, scales, resolutions, sizes, offsets,
                                            n_dense);
  const at::Tensor& grad_features = in.grad_features;
  const at::Tensor& points = in.points;
  const std::vector<Level>& levels = in.levels;
  const int64_t n_points = in.n_points, n_features = in.n_features;
  auto grad_table = at::zeros(table.sizes(), table.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hash_grid_backward_table", [&] {
    table_gradient_by_level<scalar_t>(points.data_ptr<scalar_t>(), nullptr, grad_features.data_ptr<scalar_t>(), levels,
                                      n_points, n_features, grad_table.data_ptr<scalar_t>(), nullptr);
  });
  return grad_table;
}

// d loss / d points, (N, 3), from (N, L, F) output gradients (position = x_n * s_l + 0.5).
at::Tensor hash_grid_backward_points(const at::Tensor& grad_features_in, const at::Tensor& points_in,
                                     const at::Tensor& table_in, const at::Tensor& scales,
                                     const at::Tensor& resolutions, const at::Tensor& sizes,
                                     const at::Tensor& offsets, int64_t n_dense) {
  const BackwardInputs in = backward_inputs(grad_features_in, points_in, table_in, scales, resolutions, sizes,
                                            offsets, n_dense);
  const at::Tensor &grad_features = in.grad_features, &points = in.points, &table = in.table;
  const std::vector<Level>& levels = in.levels;
  const int64_t n_points = in.n_points, n_features = in.n_features, n_levels = in.n_levels;
  auto grad_points = at::zeros({n_points, 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hash_grid_backward_points", [&] {
    const scalar_t* point_data = points.data_ptr<scalar_t>();
    const scalar_t* table_data = table.data_ptr<scalar_t>();
    const scalar_t* grad_data = grad_features.data_ptr<scalar_t>();
    scalar_t* grad_points_data = grad_points.data_ptr<scalar_t>();
    for_point_blocks(n_points, [&](int64_t begin, int64_t end) {
      Cell<scalar_t> cell;
      scalar_t term[3];
      for (int64_t l = 0; l < n_levels; ++l) {  // levels in order: each point's sum is fixed
        const Level level = levels[l];
        const scalar_t scale = static_cast<scalar_t>(level.scale);
        for (int64_t n = begin; n < end; ++n) {
          locate(point_data + 3 * n, level, cell);
          point_gradient_term(cell, table_data, grad_data + (n * n_levels + l) * n_features, n_features, scale, term);
          scalar_t* total = grad_points_data + 3 * n;
          total[0] += term[0];
          total[1] += term[1];
          total[2] += term[2];
        }
      }
    });
  });
  return grad_points;
}

// Both gradients, [d points (N, 3), d table (T, F)], locating each point on each level once (BA:
// the map and the poses are optimised together).  The point terms of all levels are kept,
// (L, N, 3), and summed over levels in order afterwards: the numbers of the two ops above.
std::vector<at::Tensor> hash_grid_backward(const at::Tensor& grad_features_in, const at::Tensor& points_in,
                                           const at::Tensor& table_in, const at::Tensor& scales,
                                           const at::Tensor& resolutions, const at::Tensor& sizes,
                                           const at::Tensor& offsets, int64_t n_dense) {
  const BackwardInputs in = backward_inputs(grad_features_in, points_in, table_in, scales, resolutions, sizes,
                                            offsets, n_dense);
  const at::Tensor& grad_features = in.grad_features;
  const at::Tensor &points = in.points, &table = in.table;
  const std::vector<Level>& levels = in.levels;
  const int64_t n_points = in.n_points, n_features = in.n_features, n_levels = in.n_levels;
  auto grad_table = at::zeros(table.sizes(), table.options());
  auto point_terms = at::empty({n_levels, n_points, 3}, points.options());
  auto grad_points = at::zeros({n_points, 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hash_grid_backward", [&] {
    table_gradient_by_level<scalar_t>(points.data_ptr<scalar_t>(), table.data_ptr<scalar_t>(),
                                      grad_features.data_ptr<scalar_t>(), levels, n_points, n_features,
                                      grad_table.data_ptr<scalar_t>(), point_terms.data_ptr<scalar_t>());
    const scalar_t* terms = point_terms.data_ptr<scalar_t>();
    scalar_t* grad_points_data = grad_points.data_ptr<scalar_t>();
    at::parallel_for(0, n_points, kSumGrain, [&](int64_t begin, int64_t end) {
      for (int64_t l = 0; l < n_levels; ++l) {  // levels in order, as hash_grid_backward_points
        for (int64_t i = 3 * begin; i < 3 * end; ++i) grad_points_data[i] += terms[l * n_points * 3 + i];
      }
    });
  });
  return {grad_points, grad_table};
}

TORCH_LIBRARY(tsslam_hash_grid, m) {
  m.def("forward", &hash_grid_forward);
  m.def("backward_table", &hash_grid_backward_table);
  m.def("backward_points", &hash_grid_backward_points);
  m.def("backward", &hash_grid_backward);
}
