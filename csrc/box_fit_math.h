// The box fit's arithmetic, shared by the CPU and CUDA kernels of box_fit: a sample's footprint
// margin and gradient row, and one Adam step, in float32 in the order the Python reference
// (t3fast.ops.reference.fit_gradient / fit_adam) evaluates them.
//
// A box is nine numbers: centre x, y (metres, relative to the agent's starting centre), velocity
// x, y (metres per step), yaw, log length, log width, acceleration x, y (metres per step^2). A
// sample is a grid column of one past frame: its centre in the present frame, its time (steps
// before the present, <= 0) and whether the agent owns it.
#pragma once

#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define T3FAST_HOST_DEVICE __host__ __device__ __forceinline__
#else
#define T3FAST_HOST_DEVICE inline
#endif

namespace t3fast {
namespace box_fit {

constexpr int kParams = 9;
constexpr int kBox = 7;  // what the op returns: the box without its acceleration
constexpr double kBeta1 = 0.9, kBeta2 = 0.999, kEps = 1e-8;  // Adam's defaults

struct alignas(16) Sample {
  float x, y, time, owned;
};

// Whether the component map frame [x, y] holds id within near columns (along each axis) of
// column (r, c): a column near the agent, which the fit samples.
T3FAST_HOST_DEVICE bool owns_near(const int64_t* frame, int64_t id, int64_t r, int64_t c,
                                  int64_t x, int64_t y, int64_t near) {
  for (int64_t rr = r - near > 0 ? r - near : 0; rr <= (r + near < x - 1 ? r + near : x - 1); ++rr) {
    for (int64_t cc = c - near > 0 ? c - near : 0; cc <= (c + near < y - 1 ? c + near : y - 1); ++cc) {
      if (frame[rr * y + cc] == id) return true;
    }
  }
  return false;
}

// The sample of column (r, c) of a frame whose planar pose in the present frame is (px, py) with
// heading cosine and sine (cs, sn): the column's centre (lower + voxel * (index + 0.5)) in the
// present frame relative to the agent's starting centre, its time and ownership.
T3FAST_HOST_DEVICE Sample sample_at(int64_t r, int64_t c, double px, double py, double cs,
                                    double sn, double lower_x, double lower_y, double voxel,
                                    const double* start, float time, bool owned) {
  const double lx = lower_x + (static_cast<double>(r) + 0.5) * voxel;
  const double ly = lower_y + (static_cast<double>(c) + 0.5) * voxel;
  const double x = px + cs * lx - sn * ly, y = py + sn * lx + cs * ly;
  return {static_cast<float>(x - start[0]), static_cast<float>(y - start[1]), time,
          owned ? 1.0f : 0.0f};
}

// What every sample of one box reads: the cosine and sine of its yaw, half its length and width.
struct Shape {
  float c, s, half_length, half_width;
};

T3FAST_HOST_DEVICE Shape shape_of(const float* p) {
  return {cosf(p[4]), sinf(p[4]), expf(p[5]) / 2.0f, expf(p[6]) / 2.0f};
}

// The sample's distances inside the footprint along and across the box (positive inside).
struct Margin {
  float along, across, by_length, by_width;
  T3FAST_HOST_DEVICE float value() const { return fminf(by_length, by_width); }
};

T3FAST_HOST_DEVICE Margin margin_of(const float* p, const Shape& b, const Sample& q) {
  const float t = q.time;
  const float cx = (p[0] + p[2] * t) + ((0.5f * p[7]) * t) * t;
  const float cy = (p[1] + p[3] * t) + ((0.5f * p[8]) * t) * t;
  const float dx = q.x - cx, dy = q.y - cy;
  const float along = b.c * dx + b.s * dy;
  const float across = -b.s * dx + b.c * dy;
  return {along, across, b.half_length - fabsf(along), b.half_width - fabsf(across)};
}

T3FAST_HOST_DEVICE float sign_of(float v) { return static_cast<float>((v > 0.0f) - (v < 0.0f)); }

// Adds the sample's gradient row of the fit loss to row[kParams]: inv_softness is 1 / the
// sigmoid's width, scale 1 / (width * samples' count). Where the two distances tie each takes
// half, as torch.minimum's gradient does.
T3FAST_HOST_DEVICE void add_gradient(const float* p, const Shape& b, const Sample& q,
                                     float softness, float scale, float* row) {
  const Margin m = margin_of(p, b, q);
  const float sigmoid = 1.0f / (1.0f + expf(-(m.value() / softness)));
  const float g = (sigmoid - q.owned) / scale;
  const float share = m.by_length < m.by_width ? 1.0f : (m.by_length == m.by_width ? 0.5f : 0.0f);
  const float g_length = g * share, g_width = g * (1.0f - share);
  const float g_along = -g_length * sign_of(m.along), g_across = -g_width * sign_of(m.across);
  const float g_x = -(g_along * b.c - g_across * b.s);
  const float g_y = -(g_along * b.s + g_across * b.c);
  const float t = q.time, half_t2 = (0.5f * t) * t;
  row[0] += g_x;
  row[1] += g_y;
  row[2] += g_x * t;
  row[3] += g_y * t;
  row[4] += g_along * m.across - g_across * m.along;
  row[5] += g_length * b.half_length;
  row[6] += g_width * b.half_width;
  row[7] += g_x * half_t2;
  row[8] += g_y * half_t2;
}

// The sigmoid's width at iteration it of iters: geometric from first to last.
T3FAST_HOST_DEVICE double softness_at(int64_t it, int64_t iters, double first, double last) {
  return first * pow(last / first, static_cast<double>(it) / static_cast<double>(iters > 1 ? iters - 1 : 1));
}

// One Adam step (iteration it, 0-based) of the nine parameters on their gradient, after the
// prior's term prior * acceleration is added to the acceleration's gradient.
T3FAST_HOST_DEVICE void adam_step(float* p, float* mean, float* square, float* grad, int64_t it,
                                  double lr, float prior) {
  grad[7] += prior * p[7];
  grad[8] += prior * p[8];
  const float bias2 = static_cast<float>(sqrt(1.0 - pow(kBeta2, static_cast<double>(it + 1))));
  const float step = static_cast<float>(-lr / (1.0 - pow(kBeta1, static_cast<double>(it + 1))));
  const float w1 = static_cast<float>(1.0 - kBeta1), w2 = static_cast<float>(1.0 - kBeta2);
  for (int k = 0; k < kParams; ++k) {
    mean[k] = mean[k] + w1 * (grad[k] - mean[k]);
    square[k] = square[k] * static_cast<float>(kBeta2) + (w2 * grad[k]) * grad[k];
    const float denom = sqrtf(square[k]) / bias2 + static_cast<float>(kEps);
    p[k] = p[k] + step * (mean[k] / denom);
  }
}

}  // namespace box_fit
}  // namespace t3fast
