// CUDA kernels of box_fit. sample_kernel: one block per (agent, frame) marks which cells of the
// agent's window are samples and writes them, in the window's row-major order, to its slice of
// the scratch (a record whose ownership is -1 is none) with their count; an agent not fitted
// writes nothing. fit_kernel: one block per fitted agent compacts its samples in order (the
// frames that hold some), then runs the Adam steps: every thread sums the
// gradient rows of its samples, a fixed-order block reduction gives the gradient, and thread 0
// steps the nine parameters. Sums run in a fixed order: the result does not vary from run to run.
#include <cuda_runtime.h>

#include <cmath>
#include <cstdint>

#include "box_fit_math.h"
#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {
namespace {

using box_fit::kParams;
using box_fit::Sample;

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;

__device__ bool fitted(double reach) { return reach > 0.0; }  // false for NaN

// Sum of v over the block into thread 0 (others get garbage), in a fixed order.
template <int N>
__device__ void block_sum(float (&v)[N], float (*scratch)[N]) {
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  for (int k = 0; k < N; ++k) {
    for (int offset = 16; offset > 0; offset /= 2) v[k] += __shfl_down_sync(0xffffffffu, v[k], offset);
  }
  if (lane == 0) {
    for (int k = 0; k < N; ++k) scratch[warp][k] = v[k];
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    for (int k = 0; k < N; ++k) {
      v[k] = scratch[0][k];
      for (int w = 1; w < kWarps; ++w) v[k] += scratch[w][k];
    }
  }
  __syncthreads();
}

__global__ void sample_kernel(BoxFitArgs a, float* samples, int* sampled) {
  __shared__ float partial[kWarps][1];
  const int64_t agent_frame = blockIdx.x;  // (window, agent, frame)
  const int t = static_cast<int>(agent_frame % a.frames);
  const int64_t agent = agent_frame / a.frames;
  const int64_t b = agent / a.count;
  const int side = 2 * a.window + 1;
  const int64_t cells = static_cast<int64_t>(side) * side;
  Sample* out = reinterpret_cast<Sample*>(samples) + agent_frame * cells;
  if (!fitted(a.reach[agent])) {  // never read: the fit skips the agent (most slots of a GPU run are empty)
    if (threadIdx.x == 0) sampled[agent_frame] = 0;
    return;
  }
  const double reach = fmin(a.reach[agent], static_cast<double>(a.window));
  const int64_t index = a.track[agent * a.frames + t];
  const double cr = a.centroid[(agent * a.frames + t) * 2], cc = a.centroid[(agent * a.frames + t) * 2 + 1];
  const bool any = index >= 0 && isfinite(cr) && isfinite(cc);
  const int r0 = any ? static_cast<int>(rint(fmin(fmax(cr, -1e9), 1e9))) : 0;
  const int c0 = any ? static_cast<int>(rint(fmin(fmax(cc, -1e9), 1e9))) : 0;
  const int64_t* frame = a.ids + (b * a.frames + t) * static_cast<int64_t>(a.x) * a.y;
  const double* pose = a.poses + (b * a.frames + t) * 3;
  const double* start = a.start + agent * box_fit::kBox;
  float found[1] = {0.0f};
  for (int64_t i = threadIdx.x; i < cells; i += blockDim.x) {
    const int dr = static_cast<int>(i / side) - a.window, dc = static_cast<int>(i % side) - a.window;
    const int r = r0 + dr, col = c0 + dc;
    Sample q{0.0f, 0.0f, 0.0f, -1.0f};
    if (any && r >= 0 && r < a.x && col >= 0 && col < a.y &&
        sqrt(static_cast<double>(dr * dr + dc * dc)) <= reach &&
        box_fit::owns_near(frame, index + 1, r, col, a.x, a.y, a.near)) {
      q = box_fit::sample_at(r, col, pose[0], pose[1], cos(pose[2]), sin(pose[2]), a.lower_x,
                             a.lower_y, a.voxel, start, static_cast<float>(t - (a.frames - 1)),
                             frame[static_cast<int64_t>(r) * a.y + col] == index + 1);
      found[0] += 1.0f;
    }
    out[i] = q;
  }
  block_sum(found, partial);
  if (threadIdx.x == 0) sampled[agent_frame] = static_cast<int>(found[0]);
}

// Moves the agent's samples (records with ownership >= 0) to the front of its slice, in order,
// reading only the frames that hold some (sampled: their counts). Returns their number (to every
// thread).
__device__ int compact(Sample* records, const int* sampled, int frames, int64_t cells) {
  __shared__ int warp_counts[kWarps];
  __shared__ int base;
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  if (threadIdx.x == 0) base = 0;
  __syncthreads();
  for (int t = 0; t < frames; ++t) {
    if (sampled[t] == 0) continue;  // the same for the whole block
    for (int64_t chunk = t * cells; chunk < (t + 1) * cells; chunk += blockDim.x) {
      const int64_t i = chunk + threadIdx.x;
      const Sample q = i < (t + 1) * cells ? records[i] : Sample{0.0f, 0.0f, 0.0f, -1.0f};
      const bool keep = q.owned >= 0.0f;
      const unsigned ballot = __ballot_sync(0xffffffffu, keep);
      if (lane == 0) warp_counts[warp] = __popc(ballot);
      __syncthreads();  // every record of the chunk is read before any is written
      int offset = base;
      for (int w = 0; w < warp; ++w) offset += warp_counts[w];
      offset += __popc(ballot & ((1u << lane) - 1u));
      if (keep) records[offset] = q;
      __syncthreads();
      if (threadIdx.x == 0) {
        for (int w = 0; w < kWarps; ++w) base += warp_counts[w];
      }
      __syncthreads();
    }
  }
  return base;
}

__global__ void fit_kernel(BoxFitArgs a, float* samples, const int* sampled, double* params,
                           double* iou) {
  __shared__ float partial[kWarps][kParams];
  __shared__ float p[kParams];
  __shared__ int window_samples, window_agents;
  const int64_t agent = blockIdx.x, b = agent / a.count;
  const double* start = a.start + agent * box_fit::kBox;
  double* out = params + agent * box_fit::kBox;
  if (!fitted(a.reach[agent])) {  // the same for the whole block
    if (threadIdx.x < box_fit::kBox) out[threadIdx.x] = start[threadIdx.x];
    if (threadIdx.x == 0) iou[agent] = 0.0;
    return;
  }
  if (threadIdx.x == 0) {
    int total = 0, agents = 0;
    for (int64_t other = b * a.count; other < (b + 1) * a.count; ++other) {
      if (!fitted(a.reach[other])) continue;
      agents += 1;
      for (int t = 0; t < a.frames; ++t) total += sampled[other * a.frames + t];
    }
    window_samples = total > 1 ? total : 1;
    window_agents = agents;
    for (int k = 0; k < kParams; ++k) p[k] = (k >= 2 && k < box_fit::kBox) ? static_cast<float>(start[k]) : 0.0f;
  }
  const int64_t side = 2 * a.window + 1;
  Sample* records = reinterpret_cast<Sample*>(samples) + agent * a.frames * side * side;
  // syncs: the shared values are set
  const int size = compact(records, sampled + agent * a.frames, a.frames, side * side);
  const auto prior = static_cast<float>(2.0 * a.accel_prior / window_agents);
  float mean[kParams] = {}, square[kParams] = {};  // thread 0's
  for (int it = 0; it < a.iters; ++it) {
    const double softness = box_fit::softness_at(it, a.iters, a.softness_first, a.softness_last);
    float local[kParams];
    for (int k = 0; k < kParams; ++k) local[k] = p[k];
    const box_fit::Shape shape = box_fit::shape_of(local);
    float grad[kParams] = {};
    for (int i = threadIdx.x; i < size; i += blockDim.x) {
      box_fit::add_gradient(local, shape, records[i], static_cast<float>(softness),
                            static_cast<float>(softness * window_samples), grad);
    }
    block_sum(grad, partial);  // ends with a barrier: every thread has read p
    if (threadIdx.x == 0) {
      box_fit::adam_step(local, mean, square, grad, it, a.lr, prior);
      for (int k = 0; k < kParams; ++k) p[k] = local[k];
    }
    __syncthreads();
  }
  float local[kParams];
  for (int k = 0; k < kParams; ++k) local[k] = p[k];
  const box_fit::Shape shape = box_fit::shape_of(local);
  float overlap[2] = {0.0f, 0.0f};  // inside and owned, inside or owned
  for (int i = threadIdx.x; i < size; i += blockDim.x) {
    const Sample q = records[i];
    const float inside = box_fit::margin_of(local, shape, q).value() > 0.0f ? 1.0f : 0.0f;
    overlap[0] += inside * q.owned;
    overlap[1] += fminf(inside + q.owned, 1.0f);
  }
  __shared__ float overlap_partial[kWarps][2];
  block_sum(overlap, overlap_partial);
  if (threadIdx.x == 0) {
    for (int k = 0; k < box_fit::kBox; ++k) out[k] = static_cast<double>(local[k]) + (k < 2 ? start[k] : 0.0);
    iou[agent] = static_cast<double>(overlap[0] / fmaxf(overlap[1], 1.0f));
  }
}

}  // namespace

int64_t box_fit_scratch(int64_t batch, int64_t count, int64_t frames, int64_t window) {
  const int64_t side = 2 * window + 1;
  return batch * count * frames * side * side;
}

cudaError_t box_fit(const BoxFitArgs& args, float* samples, int* sampled, double* params,
                    double* iou, cudaStream_t stream) {
  const int64_t agents = static_cast<int64_t>(args.batch) * args.count;
  if (agents == 0) return cudaSuccess;
  if (args.frames > 0) {
    sample_kernel<<<static_cast<unsigned>(agents * args.frames), kThreads, 0, stream>>>(args, samples, sampled);
  }
  fit_kernel<<<static_cast<unsigned>(agents), kThreads, 0, stream>>>(args, samples, sampled, params, iou);
  return cudaGetLastError();
}

}  // namespace cuda
}  // namespace t3fast
