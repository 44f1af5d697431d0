// Fused multi-resolution hash encoding on CPU: forward, backward to tables, backward to points.
//
// A torch C++ extension registered as the operator namespace `hypnerf_hashgrid`, parallelised
// with OpenMP over chunks of points (the same libgomp torch uses, so torch.set_num_threads
// applies). Semantics match the pure-PyTorch reference in model/encoding.py:
//   - coordinates are clamped into [0, 1] (NaN -> 0); the point gradient is zero outside [0, 1];
//   - a level of resolution res has res + 1 vertices per axis; the cell is
//     min(floor(x * res), res - 1), so x = 1 lands in the last cell with fraction 1 and no
//     corner leaves the grid;
//   - dense levels use row x + y (res + 1) + z (res + 1)^2, hashed levels
//     (x * 1 ^ y * 2654435761 ^ z * 805459861) mod T.
// Hash products are formed in uint32: T is a power of two <= 2^24, so the low log2(T) bits of a
// product, and of an XOR of products, are the same whether taken mod 2^32 or in int64; row
// offsets into the tables are 64-bit.
//
// Each chunk of kChunk points goes through the levels one after another, so the level's table
// stays in L1 while the chunk is processed, and chunk scratch lives on the stack: steady-state
// calls touch no freshly allocated memory apart from the returned tensors. float32 with F = 2
// runs the AVX-512 path where the CPU has it (hashgrid_avx512.h); everything else runs the
// portable path (hashgrid_portable.h).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/library.h>

#include "hashgrid_avx512.h"
#include "hashgrid_common.h"
#include "hashgrid_portable.h"

namespace {

using namespace hashgrid;

std::vector<Level> make_levels(c10::IntArrayRef resolutions, c10::IntArrayRef dense) {
  std::vector<Level> levels;
  for (size_t l = 0; l < resolutions.size(); ++l) {
    const auto r = static_cast<uint32_t>(resolutions[l]);
    levels.push_back({r, r + 1, (r + 1) * (r + 1), dense[l] != 0});
  }
  return levels;
}

struct Problem {
  int64_t batch, n, table_size, features;
  const std::vector<Level>* levels;

  int num_levels() const { return static_cast<int>(levels->size()); }
  int width() const { return num_levels() * static_cast<int>(features); }
  int64_t table_numel() const { return num_levels() * table_size * features; }
  int64_t chunks() const { return (n + kChunk - 1) / kChunk; }
};

template <typename Levels, typename T>
void forward_impl(const Problem& pb, const T* points, const T* tables, T* out) {
  const int L = pb.num_levels(), width = pb.width();
  const int64_t F = pb.features, chunks = pb.chunks(), total = pb.batch * chunks;
  const auto mask = static_cast<uint32_t>(pb.table_size - 1);
#pragma omp parallel num_threads(at::get_num_threads()) if (total > 1)
  {
    ChunkPoints<T> cp;
#pragma omp for schedule(static)
    for (int64_t job = 0; job < total; ++job) {
      const int64_t b = job / chunks, p0 = (job % chunks) * kChunk;
      cp.load(points + (b * pb.n + p0) * 3, static_cast<int>(std::min<int64_t>(kChunk, pb.n - p0)));
      T* rows = out + (b * pb.n + p0) * width;
      for (int l = 0; l < L; ++l) {
        const LevelJob<T> lj{&cp, tables + (b * L + l) * pb.table_size * F, &(*pb.levels)[l], mask, width};
        Levels::forward(lj, rows + l * F);
      }
    }
  }
}

template <typename Levels, typename T>
void backward_impl(const Problem& pb, const T* grad, const T* points, const T* tables, T* grad_tables,
                   T* grad_points) {
  const int L = pb.num_levels(), width = pb.width();
  const int64_t F = pb.features, chunks = pb.chunks(), table_numel = pb.table_numel();
  const auto mask = static_cast<uint32_t>(pb.table_size - 1);
  const int threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunks)));
  // Per-thread accumulators for the table gradient (thread 0 adds straight into the output):
  // the tables are small, so private copies plus a reduction beat atomics and cannot race.
  std::vector<T> scratch(grad_tables ? static_cast<size_t>(threads - 1) * table_numel : 0);
#pragma omp parallel num_threads(threads)
  {
    const int tid = omp_get_thread_num();
    ChunkPoints<T> cp;
    alignas(64) T gx[kChunk], gy[kChunk], gz[kChunk];
    for (int64_t b = 0; b < pb.batch; ++b) {
      T* acc = nullptr;
      if (grad_tables) {
        acc = tid == 0 ? grad_tables + b * table_numel : scratch.data() + (tid - 1) * table_numel;
        if (tid != 0) std::fill(acc, acc + table_numel, T(0));
      }
#pragma omp for schedule(static)
      for (int64_t chunk = 0; chunk < chunks; ++chunk) {
        const int64_t p0 = chunk * kChunk;
        const T* pts = points + (b * pb.n + p0) * 3;
        cp.load(pts, static_cast<int>(std::min<int64_t>(kChunk, pb.n - p0)));
        std::fill(gx, gx + kChunk, T(0));
        std::fill(gy, gy + kChunk, T(0));
        std::fill(gz, gz + kChunk, T(0));
        const T* rows = grad + (b * pb.n + p0) * width;
        for (int l = 0; l < L; ++l) {
          const int64_t offset = l * pb.table_size * F;
          const LevelJob<T> lj{&cp, tables + b * table_numel + offset, &(*pb.levels)[l], mask, width};
          Levels::backward(lj, rows + l * F, acc ? acc + offset : nullptr, grad_points ? gx : nullptr, gy, gz);
        }
        if (grad_points) {
          T* gp = grad_points + (b * pb.n + p0) * 3;
          for (int p = 0; p < cp.n; ++p) {
            gp[3 * p + 0] = gx[p] * inside01(pts[3 * p + 0]);
            gp[3 * p + 1] = gy[p] * inside01(pts[3 * p + 1]);
            gp[3 * p + 2] = gz[p] * inside01(pts[3 * p + 2]);
          }
        }
      }  // implicit barrier: every thread's accumulator for object b is complete
      if (grad_tables && threads > 1) {
        T* out = grad_tables + b * table_numel;
#pragma omp for schedule(static)
        for (int64_t e = 0; e < table_numel; ++e) {
          T s = out[e];
          for (int t = 0; t < threads - 1; ++t) s += scratch[t * table_numel + e];
          out[e] = s;
        }
      }
    }
  }
}

// Picks the level kernels for a dtype and feature width; each width is its own instantiation so
// the per-corner feature loop fully unrolls.
template <typename T, typename Fn>
void with_levels(int64_t features, Fn&& fn) {
#ifdef HASHGRID_HAVE_AVX512
  if constexpr (std::is_same_v<T, float>) {
    if (features == 2) return fn(Avx512PairLevels{});
  }
#endif
  switch (features) {
    case 1: return fn(PortableLevels<T, 1>{});
    case 2: return fn(PortableLevels<T, 2>{});
    case 4: return fn(PortableLevels<T, 4>{});
    case 8: return fn(PortableLevels<T, 8>{});
    default: TORCH_CHECK(false, "hashgrid kernel supports 1, 2, 4 or 8 features per level, got ", features);
  }
}

void check_inputs(const at::Tensor& points, const at::Tensor& tables, c10::IntArrayRef resolutions,
                  c10::IntArrayRef dense) {
  TORCH_CHECK(points.device().is_cpu() && tables.device().is_cpu(), "hashgrid kernel runs on CPU tensors");
  TORCH_CHECK(points.dim() == 3 && points.size(2) == 3, "points must be [B, N, 3]");
  TORCH_CHECK(tables.dim() == 4 && tables.size(0) == points.size(0), "tables must be [B, L, T, F]");
  TORCH_CHECK(points.is_contiguous() && tables.is_contiguous(), "points and tables must be contiguous");
  TORCH_CHECK(points.scalar_type() == tables.scalar_type(), "points and tables must share a dtype");
  TORCH_CHECK(static_cast<int64_t>(resolutions.size()) == tables.size(1) &&
                  static_cast<int64_t>(dense.size()) == tables.size(1),
              "one resolution and dense flag per level");
  const int64_t t = tables.size(1) > 0 ? tables.size(2) : 1;
  TORCH_CHECK(t > 0 && (t & (t - 1)) == 0 && t <= (int64_t(1) << 24), "table size must be a power of two <= 2^24");
  for (auto r : resolutions) TORCH_CHECK(r >= 1 && r < (int64_t(1) << 20), "level resolution out of range");
}

at::Tensor hashgrid_forward(const at::Tensor& points, const at::Tensor& tables, c10::IntArrayRef resolutions,
                            c10::IntArrayRef dense) {
  check_inputs(points, tables, resolutions, dense);
  const int64_t B = points.size(0), N = points.size(1), L = tables.size(1), T = tables.size(2), F = tables.size(3);
  auto out = at::empty({B, N, L * F}, points.options());
  if (out.numel() == 0) return out;
  const auto levels = make_levels(resolutions, dense);
  const Problem pb{B, N, T, F, &levels};
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_forward", [&] {
    with_levels<scalar_t>(F, [&](auto kernel) {
      forward_impl<decltype(kernel)>(pb, points.const_data_ptr<scalar_t>(), tables.const_data_ptr<scalar_t>(),
                                     out.mutable_data_ptr<scalar_t>());
    });
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> hashgrid_backward(const at::Tensor& grad, const at::Tensor& points,
                                                     const at::Tensor& tables, c10::IntArrayRef resolutions,
                                                     c10::IntArrayRef dense, bool need_tables,
                                                     bool need_points) {
  check_inputs(points, tables, resolutions, dense);
  const int64_t B = points.size(0), N = points.size(1), L = tables.size(1), T = tables.size(2), F = tables.size(3);
  TORCH_CHECK(grad.is_contiguous() && grad.scalar_type() == points.scalar_type() && grad.dim() == 3 &&
                  grad.size(0) == B && grad.size(1) == N && grad.size(2) == L * F,
              "grad must be a contiguous [B, N, L*F] tensor of the points' dtype");
  // Outputs that are not requested stay empty.
  auto grad_tables = need_tables ? at::zeros(tables.sizes(), tables.options()) : at::empty({0}, tables.options());
  auto grad_points = need_points ? at::empty(points.sizes(), points.options()) : at::empty({0}, points.options());
  if (N == 0 || L == 0 || !(need_tables || need_points)) {
    if (need_points) grad_points.zero_();
    return {grad_tables, grad_points};
  }
  const auto levels = make_levels(resolutions, dense);
  const Problem pb{B, N, T, F, &levels};
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_backward", [&] {
    with_levels<scalar_t>(F, [&](auto kernel) {
      backward_impl<decltype(kernel)>(pb, grad.const_data_ptr<scalar_t>(), points.const_data_ptr<scalar_t>(),
                                      tables.const_data_ptr<scalar_t>(),
                                      need_tables ? grad_tables.mutable_data_ptr<scalar_t>() : nullptr,
                                      need_points ? grad_points.mutable_data_ptr<scalar_t>() : nullptr);
    });
  });
  return {grad_tables, grad_points};
}

}  // namespace

TORCH_LIBRARY(hypnerf_hashgrid, m) {
  m.def("forward(Tensor points, Tensor tables, int[] resolutions, int[] dense) -> Tensor");
  m.def(
      "backward(Tensor grad, Tensor points, Tensor tables, int[] resolutions, int[] dense, bool need_tables, "
      "bool need_points) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(hypnerf_hashgrid, CPU, m) {
  m.impl("forward", hashgrid_forward);
  m.impl("backward", hashgrid_backward);
}
