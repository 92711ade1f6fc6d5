// CUDA kernels of bev_components: a concurrent union-find over the cells of the masks, one
// thread per cell. Every parent pointer points to a cell at or after its own (a root points to
// itself), and a union always hangs the smaller root under the larger one with a compare-and-swap,
// so each component's root ends as its last cell whatever order the threads run in.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;

// The root of cell i, halving the path on the way: pointing a cell at its grandparent keeps it
// in its tree whatever other threads link meanwhile (pointers only ever move forward).
__device__ int find_root(int* parent, int i) {
  int cur = parent[i];
  if (cur == i) return i;
  int prev = i;
  int next;
  while ((next = parent[cur]) != cur) {
    parent[prev] = next;
    prev = cur;
    cur = next;
  }
  return cur;
}

__device__ void unite(int* parent, int a, int b) {
  a = find_root(parent, a);
  b = find_root(parent, b);
  while (a != b) {
    if (a > b) {
      const int t = a;
      a = b;
      b = t;
    }
    const int old = atomicCAS(parent + a, a, b);
    if (old == a) return;  // linked
    a = find_root(parent, old);  // another thread linked a first: go on from its new root
    b = find_root(parent, b);
  }
}

__global__ void init_kernel(int total, int* parent) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < total) parent[i] = i;
}

// Each cell on the mask joins its four neighbours before it (left, and the three of the row
// above): the other four join it from their side.
__global__ void unite_kernel(const bool* mask, int total, int x, int y, int* parent) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= total || !mask[i]) return;
  const int cell = i % (x * y);
  const int row = cell / y, col = cell - row * y;
  if (col > 0 && mask[i - 1]) unite(parent, i, i - 1);
  if (row == 0) return;
  for (int d = -1; d <= 1; ++d) {
    const int c = col + d;
    if (c >= 0 && c < y && mask[i - y + d]) unite(parent, i, i - y + d);
  }
}

__global__ void flatten_kernel(const bool* mask, int total, int* parent) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= total) return;
  parent[i] = mask[i] ? find_root(parent, i) : -1;
}

}  // namespace

cudaError_t bev_component_roots(const bool* mask, int64_t batch, int x, int y, int* parent,
                                cudaStream_t stream) {
  const int64_t cells = batch * x * y;
  if (cells == 0) return cudaSuccess;
  const int total = static_cast<int>(cells);  // the glue refuses 2^31 cells or more
  const unsigned blocks = static_cast<unsigned>((cells + kThreads - 1) / kThreads);
  init_kernel<<<blocks, kThreads, 0, stream>>>(total, parent);
  unite_kernel<<<blocks, kThreads, 0, stream>>>(mask, total, x, y, parent);
  flatten_kernel<<<blocks, kThreads, 0, stream>>>(mask, total, parent);
  return cudaGetLastError();
}

}  // namespace cuda
}  // namespace t3fast
