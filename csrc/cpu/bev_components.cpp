// CPU kernel of bev_components: the 8-connected components of a BEV mask, numbered 1..n in the
// order of each component's last cell (row-major), 0 off the mask. One union-find per mask (the
// batch in parallel): a single raster pass links every cell to its four neighbours already seen
// (up-left, up, up-right, left), always hanging the smaller root under the larger, so that each
// component's root is its last cell; a second pass numbers the roots in order, a third gives
// every cell its root's number.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

#include "checks.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "bev_components";

// The root of cell i, halving the path on the way (every cell then points two steps closer).
inline int64_t find_root(std::vector<int64_t>& parent, int64_t i) {
  while (parent[i] != i) {
    parent[i] = parent[parent[i]];
    i = parent[i];
  }
  return i;
}

inline void unite(std::vector<int64_t>& parent, int64_t a, int64_t b) {
  a = find_root(parent, a);
  b = find_root(parent, b);
  if (a == b) return;
  if (a > b) std::swap(a, b);
  parent[a] = b;  // the larger root stays: a component's root is its last cell
}

// One mask [X, Y] -> labels [X, Y]; returns the number of components.
int64_t label_components(const bool* mask, int64_t X, int64_t Y, int64_t* labels,
                         std::vector<int64_t>& parent) {
  const int64_t n = X * Y;
  parent.resize(n);
  for (int64_t i = 0; i < n; ++i) parent[i] = i;
  for (int64_t x = 0; x < X; ++x) {
    for (int64_t y = 0; y < Y; ++y) {
      const int64_t i = x * Y + y;
      if (!mask[i]) continue;
      if (y > 0 && mask[i - 1]) unite(parent, i, i - 1);
      if (x == 0) continue;
      for (int64_t dy = -1; dy <= 1; ++dy) {
        const int64_t ny = y + dy;
        if (ny >= 0 && ny < Y && mask[i - Y + dy]) unite(parent, i, i - Y + dy);
      }
    }
  }
  // number the roots in order (labels holds each root's number for now), then every cell
  int64_t count = 0;
  for (int64_t i = 0; i < n; ++i) labels[i] = mask[i] && find_root(parent, i) == i ? ++count : 0;
  for (int64_t i = 0; i < n; ++i) {
    if (mask[i]) labels[i] = labels[find_root(parent, i)];
  }
  return count;
}

std::tuple<at::Tensor, at::Tensor> bev_components_cpu(const at::Tensor& mask) {
  check_bev_mask(mask, kOp);
  const at::Tensor m = mask.contiguous();
  const int64_t B = m.size(0), X = m.size(1), Y = m.size(2);
  at::Tensor labels = at::empty({B, X, Y}, m.options().dtype(at::kLong));
  at::Tensor count = at::empty({B}, m.options().dtype(at::kLong));
  const bool* pm = m.data_ptr<bool>();
  int64_t* pl = labels.data_ptr<int64_t>();
  int64_t* pc = count.data_ptr<int64_t>();
  // a thread per 2^18 cells at least: a 200 x 200 mask takes tens of microseconds, less than
  // waking a second thread on a busy machine
  const int64_t grain = std::max<int64_t>(1, (int64_t{1} << 18) / std::max<int64_t>(1, X * Y));
  at::parallel_for(0, B, grain, [&](int64_t b0, int64_t b1) {
    std::vector<int64_t> parent;
    for (int64_t b = b0; b < b1; ++b) {
      pc[b] = label_components(pm + b * X * Y, X, Y, pl + b * X * Y, parent);
    }
  });
  return {labels, count};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) { m.impl("bev_components", &bev_components_cpu); }

}  // namespace t3fast
