// CPU kernel of box_fit: each agent's samples gathered in the reference's order (frames, then
// window rows, then columns), then its box fitted by Adam on the closed-form gradient
// (box_fit_math.h), the agents of all windows in parallel. Every agent's sums run in one
// thread in a fixed order, so the result does not depend on the thread count.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

#include "box_fit_math.h"
#include "checks.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "box_fit";
using box_fit::kParams;
using box_fit::Sample;

struct Grid {
  int64_t T, X, Y;
  double lower_x, lower_y, voxel;
  int64_t near;
};

// One agent's samples (see t3fast.ops.reference.box_fit_samples): ids [T, X, Y], track [T],
// centroid [T, 2], poses [T, 3], start [7].
std::vector<Sample> collect(const int64_t* ids, const int64_t* track, const double* centroid,
                            const double* poses, const double* start, double reach,
                            const Grid& g) {
  std::vector<Sample> out;
  const auto half = static_cast<int64_t>(std::ceil(reach));
  for (int64_t t = 0; t < g.T; ++t) {
    const int64_t index = track[t];
    const double cr = centroid[2 * t], cc = centroid[2 * t + 1];
    if (index < 0 || !std::isfinite(cr) || !std::isfinite(cc)) continue;
    const int64_t* frame = ids + t * g.X * g.Y;
    const auto r0 = static_cast<int64_t>(std::nearbyint(std::clamp(cr, -1e9, 1e9)));
    const auto c0 = static_cast<int64_t>(std::nearbyint(std::clamp(cc, -1e9, 1e9)));
    const double* pose = poses + 3 * t;
    const double c = std::cos(pose[2]), s = std::sin(pose[2]);
    const auto time = static_cast<float>(t - (g.T - 1));
    for (int64_t dr = -half; dr <= half; ++dr) {
      const int64_t r = r0 + dr;
      if (r < 0 || r >= g.X) continue;
      for (int64_t dc = -half; dc <= half; ++dc) {
        const int64_t col = c0 + dc;
        if (col < 0 || col >= g.Y) continue;
        if (std::sqrt(static_cast<double>(dr * dr + dc * dc)) > reach) continue;
        if (!box_fit::owns_near(frame, index + 1, r, col, g.X, g.Y, g.near)) continue;
        out.push_back(box_fit::sample_at(r, col, pose[0], pose[1], c, s, g.lower_x, g.lower_y,
                                         g.voxel, start, time, frame[r * g.Y + col] == index + 1));
      }
    }
  }
  return out;
}

struct Fit {
  int64_t iters;
  double lr, softness_first, softness_last, accel_prior;
};

// One agent's box fitted to its samples; count and agents: the window's samples and agents
// fitted (the loss's and the prior's normalisers). Writes params [7] and iou.
void fit(const std::vector<Sample>& samples, const double* start, int64_t count, int64_t agents,
         const Fit& f, double* params, double* iou) {
  float p[kParams] = {0.0f, 0.0f};
  for (int k = 2; k < box_fit::kBox; ++k) p[k] = static_cast<float>(start[k]);
  float mean[kParams] = {}, square[kParams] = {};
  const auto prior = static_cast<float>(2.0 * f.accel_prior / static_cast<double>(agents));
  const auto total = static_cast<double>(std::max<int64_t>(count, 1));
  for (int64_t it = 0; it < f.iters; ++it) {
    const double softness = box_fit::softness_at(it, f.iters, f.softness_first, f.softness_last);
    const box_fit::Shape b = box_fit::shape_of(p);
    float grad[kParams] = {};
    for (const Sample& q : samples) {
      box_fit::add_gradient(p, b, q, static_cast<float>(softness),
                            static_cast<float>(softness * total), grad);
    }
    box_fit::adam_step(p, mean, square, grad, it, f.lr, prior);
  }
  const box_fit::Shape b = box_fit::shape_of(p);
  float both = 0.0f, either = 0.0f;
  for (const Sample& q : samples) {
    const float inside = box_fit::margin_of(p, b, q).value() > 0.0f ? 1.0f : 0.0f;
    both += inside * q.owned;
    either += std::min(inside + q.owned, 1.0f);
  }
  for (int k = 0; k < box_fit::kBox; ++k) {
    params[k] = static_cast<double>(p[k]) + (k < 2 ? start[k] : 0.0);
  }
  *iou = static_cast<double>(both / std::max(either, 1.0f));
}

std::tuple<at::Tensor, at::Tensor> box_fit_cpu(
    const at::Tensor& ids, const at::Tensor& track, const at::Tensor& centroid,
    const at::Tensor& poses, const at::Tensor& start, const at::Tensor& reach,
    c10::ArrayRef<double> lower, double voxel_size, int64_t window, int64_t near, int64_t iters,
    double lr, c10::ArrayRef<double> softness, double accel_prior) {
  check_box_fit(ids, track, centroid, poses, start, reach, lower, voxel_size, window, near, iters,
                lr, softness, kOp);
  const at::Tensor id = ids.contiguous(), tr = track.contiguous(), ce = centroid.contiguous(),
                   po = poses.contiguous(), st = start.contiguous(), re = reach.contiguous();
  at::Tensor params = st.clone(), iou = at::zeros(re.sizes(), re.options());
  const int64_t B = id.size(0), T = id.size(1), n = tr.size(1);
  const Grid g{T, id.size(2), id.size(3), lower[0], lower[1], voxel_size, near};
  const Fit f{iters, lr, softness[0], softness[1], accel_prior};
  const int64_t* pid = id.data_ptr<int64_t>();
  const int64_t* ptr = tr.data_ptr<int64_t>();
  const double *pce = ce.data_ptr<double>(), *ppo = po.data_ptr<double>(),
               *pst = st.data_ptr<double>(), *pre = re.data_ptr<double>();
  std::vector<std::vector<Sample>> samples(B * n);
  at::parallel_for(0, B * n, 1, [&](int64_t a0, int64_t a1) {
    for (int64_t a = a0; a < a1; ++a) {
      if (!(pre[a] > 0)) continue;  // not fitted (NaN included)
      const int64_t b = a / n;
      samples[a] = collect(pid + b * T * g.X * g.Y, ptr + a * T, pce + a * T * 2, ppo + b * T * 3,
                           pst + a * box_fit::kBox, std::min(pre[a], static_cast<double>(window)), g);
    }
  });
  std::vector<int64_t> count(B, 0), agents(B, 0);
  for (int64_t a = 0; a < B * n; ++a) {
    if (pre[a] > 0) {
      count[a / n] += static_cast<int64_t>(samples[a].size());
      agents[a / n] += 1;
    }
  }
  double* pparams = params.data_ptr<double>();
  double* piou = iou.data_ptr<double>();
  at::parallel_for(0, B * n, 1, [&](int64_t a0, int64_t a1) {
    for (int64_t a = a0; a < a1; ++a) {
      if (!(pre[a] > 0)) continue;
      fit(samples[a], pst + a * box_fit::kBox, count[a / n], agents[a / n], f,
          pparams + a * box_fit::kBox, piou + a);
    }
  });
  return {params, iou};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) { m.impl("box_fit", &box_fit_cpu); }

}  // namespace t3fast
