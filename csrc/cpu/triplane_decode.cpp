// CPU kernels of triplane_decode and its backward.
//
// Query points are processed in cache-sized chunks (kChunk points); a chunk's features and
// hidden activations live in per-thread buffers, and each linear layer is one GEMM on the
// chunk, so the [all points, hidden] tensors of the reference never exist.
//
// Full-grid mode uses that the first layer is linear in the features, and the features are
// a sum of per-plane lookups and per-axis encodings:
//   W0 [xy(x,y) + xz(x,z) + yz(y,z); PE(x,y,z)] + b0 = T_xy[i,j] + T_xz[i,k] + T_yz[j,k]
// where T_xy = lookup of (W0_c xy) at (i,j) + W0_pe,x PE(x_i) + W0_pe,y PE(y_j) + b0, and so
// on. The tables are built once per batch element (X*Y + X*Z + Y*Z rows instead of X*Y*Z),
// which removes the first layer's GEMM and all sin/cos from the per-voxel work.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include "cpu/simd.h"
#include "triplane_args.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "triplane_decode";
constexpr const char* kOpBwd = "triplane_decode_backward";
constexpr int64_t kChunk = 1024;  // points per GEMM; [kChunk, 256] floats = 1 MiB

// Linear-interpolation taps along one plane axis of `size` cells, grid_sample's
// align_corners=False convention with border clamping.
template <typename T>
struct Tap {
  int64_t i0, i1;
  T w1;  // weight of i1; i0 gets 1 - w1
};

template <typename T>
inline Tap<T> make_tap(T q, int64_t size) {
  T u = ((q + T(1)) * T(size) - T(1)) / T(2);
  u = std::min<T>(std::max<T>(u, T(0)), T(size - 1));
  const T f = std::floor(u);
  const int64_t i0 = static_cast<int64_t>(f);
  return {i0, std::min<int64_t>(i0 + 1, size - 1), u - f};
}

// Voxel-centre coordinate of cell i of n: (2 i + 1) / n - 1.
template <typename T>
inline T cell_centre(int64_t i, int64_t n) {
  return T(2 * i + 1) / T(n) - T(1);
}

// acc[0:n] += w * row[0:n]
template <typename T>
inline void axpy(T* __restrict acc, const T* __restrict row, T w, int64_t n) {
  for (int64_t c = 0; c < n; ++c) acc[c] += w * row[c];
}

// out[0:n] = bilinear lookup of a channels-last plane [rows, cols, n] at (tr, tc).
template <typename T>
inline void lookup(T* __restrict out, const T* plane, int64_t cols, int64_t n, const Tap<T>& tr,
                   const Tap<T>& tc) {
  const T wr0 = T(1) - tr.w1, wc0 = T(1) - tc.w1;
  const T* r0 = plane + tr.i0 * cols * n;
  const T* r1 = plane + tr.i1 * cols * n;
  axpy(out, r0 + tc.i0 * n, wr0 * wc0, n);
  axpy(out, r0 + tc.i1 * n, wr0 * tc.w1, n);
  axpy(out, r1 + tc.i0 * n, tr.w1 * wc0, n);
  axpy(out, r1 + tc.i1 * n, tr.w1 * tc.w1, n);
}

// Transposed lookup: scatter g[0:n] into the plane's four taps.
template <typename T>
inline void scatter(T* plane, int64_t cols, int64_t n, const Tap<T>& tr, const Tap<T>& tc,
                    const T* __restrict g) {
  const T wr0 = T(1) - tr.w1, wc0 = T(1) - tc.w1;
  T* r0 = plane + tr.i0 * cols * n;
  T* r1 = plane + tr.i1 * cols * n;
  axpy(r0 + tc.i0 * n, g, wr0 * wc0, n);
  axpy(r0 + tc.i1 * n, g, wr0 * tc.w1, n);
  axpy(r1 + tc.i0 * n, g, tr.w1 * wc0, n);
  axpy(r1 + tc.i1 * n, g, tr.w1 * tc.w1, n);
}

template <typename T>
T3FAST_SIMD_CLONES void relu_inplace(T* x, int64_t n) {
  // written so that NaN stays NaN, as in torch.relu
  for (int64_t i = 0; i < n; ++i) x[i] = x[i] < T(0) ? T(0) : x[i];
}

// ReLU backward: the gradient is zero where the layer's output was clamped.
template <typename T>
T3FAST_SIMD_CLONES void relu_backward(T* grad, const T* out, int64_t n) {
  for (int64_t i = 0; i < n; ++i) grad[i] = out[i] > T(0) ? grad[i] : T(0);
}

// Everything the kernels need to know about one call: the checked sizes and the tensors,
// contiguous, with channels-last planes.
struct Problem : TriplaneProblem {
  at::Tensor xy, xz, yz;  // [B, X', Y', C], [B, X', Z', C], [B, Y', Z', C]
  std::vector<at::Tensor> weights, biases;
  at::Tensor points;  // [B, N, 3], or undefined (grid mode)

  explicit Problem(TriplaneProblem sizes) : TriplaneProblem(std::move(sizes)) {}
};

Problem make_problem(TriplaneProblem sizes, const at::Tensor& xy, const at::Tensor& xz,
                     const at::Tensor& yz, at::TensorList weights, at::TensorList biases,
                     const c10::optional<at::Tensor>& points) {
  Problem p(std::move(sizes));
  // Detached: the worker threads of at::parallel_for do not inherit the caller's dispatch
  // guards, and the GEMMs they run must not see tensors that require grad.
  p.xy = xy.detach().permute({0, 2, 3, 1}).contiguous();
  p.xz = xz.detach().permute({0, 2, 3, 1}).contiguous();
  p.yz = yz.detach().permute({0, 2, 3, 1}).contiguous();
  for (size_t i = 0; i < weights.size(); ++i) {
    p.weights.push_back(weights[i].detach().contiguous());
    p.biases.push_back(biases[i].detach().contiguous());
  }
  if (points.has_value()) p.points = points->detach().contiguous();
  return p;
}

// Coordinates of query n (flat over batch and points/voxels).
template <typename T>
inline void query_coords(const Problem& p, const T* pts, int64_t n, T& x, T& y, T& z) {
  if (pts != nullptr) {
    x = pts[3 * n];
    y = pts[3 * n + 1];
    z = pts[3 * n + 2];
    return;
  }
  const int64_t v = n % p.per_batch;
  x = cell_centre<T>(v / (p.GY * p.GZ), p.GX);
  y = cell_centre<T>((v / p.GZ) % p.GY, p.GY);
  z = cell_centre<T>(v % p.GZ, p.GZ);
}

// Decoder input features of queries [start, start + count) into feat [count, in_0].
template <typename T>
T3FAST_SIMD_CLONES void fill_features(const Problem& p, int64_t start, int64_t count, T* feat) {
  const T* xy = p.xy.data_ptr<T>();
  const T* xz = p.xz.data_ptr<T>();
  const T* yz = p.yz.data_ptr<T>();
  const T* pts = p.points.defined() ? p.points.data_ptr<T>() : nullptr;
  const int64_t in0 = p.widths[0];
  for (int64_t r = 0; r < count; ++r) {
    const int64_t n = start + r;
    const int64_t b = n / p.per_batch;
    T x, y, z;
    query_coords(p, pts, n, x, y, z);
    const Tap<T> tx = make_tap(x, p.PX), ty = make_tap(y, p.PY), tz = make_tap(z, p.PZ);
    T* f = feat + r * in0;
    std::fill(f, f + p.C, T(0));
    lookup(f, xy + b * p.PX * p.PY * p.C, p.PY, p.C, tx, ty);
    lookup(f, xz + b * p.PX * p.PZ * p.C, p.PZ, p.C, tx, tz);
    lookup(f, yz + b * p.PY * p.PZ * p.C, p.PZ, p.C, ty, tz);
    T* pe = f + p.C;
    for (int64_t k = 0; k < p.pe_freqs; ++k) {
      const T s = T(int64_t(1) << k);
      pe[6 * k + 0] = std::sin(x * s);
      pe[6 * k + 1] = std::sin(y * s);
      pe[6 * k + 2] = std::sin(z * s);
      pe[6 * k + 3] = std::cos(x * s);
      pe[6 * k + 4] = std::cos(y * s);
      pe[6 * k + 5] = std::cos(z * s);
    }
  }
}

// 2-D view [rows, cols] of the start of a flat per-thread buffer.
inline at::Tensor view2d(const at::Tensor& flat, int64_t rows, int64_t cols) {
  return flat.narrow(0, 0, rows * cols).view({rows, cols});
}

// First index of the maximum of each row of logits [rows, K], like torch.argmax: NaN counts
// as larger than every number, so a row's first NaN wins (as in the CUDA kernel).
template <typename T>
T3FAST_SIMD_CLONES void argmax_rows(const T* logits, int64_t rows, int64_t K, uint8_t* out) {
  for (int64_t r = 0; r < rows; ++r) {
    const T* row = logits + r * K;
    int64_t best = 0;
    T best_value = row[0];
    for (int64_t k = 1; k < K; ++k) {
      const T v = row[k];
      if (v > best_value || (v != v && best_value == best_value)) {
        best = k;
        best_value = v;
      }
    }
    out[r] = static_cast<uint8_t>(best);
  }
}

// Writes a chunk's result: logits rows, or the first-max class as uint8.
template <typename T>
void emit(const at::Tensor& logits_chunk, at::Tensor& out, int64_t start, bool argmax) {
  const int64_t rows = logits_chunk.size(0), K = logits_chunk.size(1);
  if (!argmax) {
    out.view({-1, K}).narrow(0, start, rows).copy_(logits_chunk);
    return;
  }
  argmax_rows(logits_chunk.data_ptr<T>(), rows, K, out.data_ptr<uint8_t>() + start);
}

// Layers first..L-1 on a chunk whose input activations are `h` [rows, widths[first]].
// Returns the logits of the chunk; in logits mode they are written straight into `out`.
template <typename T>
at::Tensor run_layers(const Problem& p, int64_t first, at::Tensor h, at::Tensor& ping,
                      at::Tensor& pong, at::Tensor& out, int64_t start, bool argmax) {
  const int64_t rows = h.size(0), L = p.layers();
  for (int64_t l = first; l < L; ++l) {
    const int64_t width = p.widths[l + 1];
    at::Tensor dst;
    if (l + 1 == L && !argmax) {
      dst = out.view({-1, width}).narrow(0, start, rows);
    } else {
      dst = view2d(h.data_ptr() == ping.data_ptr() ? pong : ping, rows, width);
    }
    at::addmm_out(dst, p.biases[l], h, p.weights[l].t());
    if (l + 1 < L) relu_inplace(dst.data_ptr<T>(), rows * width);
    h = dst;
  }
  return h;
}

// Forward with explicit features per chunk (points mode). With `live` (one count per batch
// element, clamped to [0, N]) only each element's first live[b] points are decoded.
template <typename T>
void forward_features(const Problem& p, at::Tensor& out, bool argmax, const int64_t* live) {
  std::vector<std::pair<int64_t, int64_t>> ranges;  // (first query, count) to decode
  if (live == nullptr) {
    ranges.emplace_back(0, p.B * p.per_batch);
  } else {
    for (int64_t b = 0; b < p.B; ++b) {
      ranges.emplace_back(b * p.per_batch, std::clamp<int64_t>(live[b], 0, p.per_batch));
    }
  }
  std::vector<std::pair<int64_t, int64_t>> chunks;  // (start, rows)
  for (const auto& [first, count] : ranges) {
    for (int64_t c = 0; c < count; c += kChunk) chunks.emplace_back(first + c, std::min(kChunk, count - c));
  }
  const auto opts = p.xy.options();
  at::parallel_for(0, static_cast<int64_t>(chunks.size()), 1, [&](int64_t begin, int64_t end) {
    at::Tensor feat = at::empty({kChunk * p.widths[0]}, opts);
    at::Tensor ping = at::empty({kChunk * p.max_width()}, opts);
    at::Tensor pong = at::empty({kChunk * p.max_width()}, opts);
    for (int64_t c = begin; c < end; ++c) {
      const auto [start, rows] = chunks[c];
      fill_features<T>(p, start, rows, feat.data_ptr<T>());
      at::Tensor logits =
          run_layers<T>(p, 0, view2d(feat, rows, p.widths[0]), ping, pong, out, start, argmax);
      if (argmax) emit<T>(logits, out, start, true);
    }
  });
}

// PE columns of W0 belonging to one axis (0 = x, 1 = y, 2 = z): [H0, 2F] ordered
// (sin 2^0, cos 2^0, sin 2^1, ...), and that axis' encodings [n, 2F] for n cells.
template <typename T>
at::Tensor axis_encoding_contribution(const Problem& p, int axis, int64_t n) {
  const int64_t F = p.pe_freqs, H0 = p.widths[1];
  if (F == 0) return at::zeros({n, H0}, p.xy.options());
  std::vector<int64_t> cols;
  for (int64_t k = 0; k < F; ++k) {
    cols.push_back(p.C + 6 * k + axis);
    cols.push_back(p.C + 6 * k + 3 + axis);
  }
  const at::Tensor idx = at::tensor(cols, at::kLong);
  const at::Tensor w = p.weights[0].index_select(1, idx);  // [H0, 2F]
  at::Tensor enc = at::empty({n, 2 * F}, p.xy.options());
  T* e = enc.data_ptr<T>();
  for (int64_t i = 0; i < n; ++i) {
    const T q = cell_centre<T>(i, n);
    for (int64_t k = 0; k < F; ++k) {
      const T s = T(int64_t(1) << k);
      e[i * 2 * F + 2 * k] = std::sin(q * s);
      e[i * 2 * F + 2 * k + 1] = std::cos(q * s);
    }
  }
  return at::mm(enc, w.t());  // [n, H0]
}

template <typename T>
T3FAST_SIMD_CLONES void fill_table_rows(T* table, int64_t r0, int64_t r1, const T* proj,
                                        int64_t cols, int64_t H, const Tap<T>* tr,
                                        const Tap<T>* tc, int64_t S, const T* row_add,
                                        const T* col_add, const T* bias) {
  for (int64_t r = r0; r < r1; ++r) {
    for (int64_t s = 0; s < S; ++s) {
      T* o = table + (r * S + s) * H;
      std::fill(o, o + H, T(0));
      if (row_add != nullptr) axpy(o, row_add + r * H, T(1), H);
      if (col_add != nullptr) axpy(o, col_add + s * H, T(1), H);
      if (bias != nullptr) axpy(o, bias, T(1), H);
      lookup(o, proj, cols, H, tr[r], tc[s]);
    }
  }
}

// table[r, s, :] = lookup of the projected plane [rows, cols, H] at (row tap r, col tap s)
// + sum of the optional per-row [R, H] / per-column [S, H] / constant [H] terms.
template <typename T>
at::Tensor sample_table(const at::Tensor& proj, int64_t cols, const std::vector<Tap<T>>& tr,
                        const std::vector<Tap<T>>& tc, const T* row_add, const T* col_add,
                        const T* bias) {
  const int64_t R = static_cast<int64_t>(tr.size()), S = static_cast<int64_t>(tc.size());
  const int64_t H = proj.size(-1);
  at::Tensor table = at::empty({R, S, H}, proj.options());
  const T* pr = proj.data_ptr<T>();
  T* t = table.data_ptr<T>();
  at::parallel_for(0, R, 1, [&](int64_t r0, int64_t r1) {
    fill_table_rows(t, r0, r1, pr, cols, H, tr.data(), tc.data(), S, row_add, col_add, bias);
  });
  return table;
}

template <typename T>
std::vector<Tap<T>> axis_taps(int64_t grid_cells, int64_t plane_cells) {
  std::vector<Tap<T>> taps;
  taps.reserve(grid_cells);
  for (int64_t i = 0; i < grid_cells; ++i) {
    taps.push_back(make_tap(cell_centre<T>(i, grid_cells), plane_cells));
  }
  return taps;
}

// First-layer pre-activations of voxels [v0, v0 + rows) of one batch element:
// h[r] = T_xy[i, j] + T_xz[i, k] + T_yz[j, k].
template <typename T>
T3FAST_SIMD_CLONES void sum_tables(T* h, int64_t v0, int64_t rows, const T* txy, const T* txz,
                                   const T* tyz, int64_t GY, int64_t GZ, int64_t H) {
  for (int64_t r = 0; r < rows; ++r) {
    const int64_t v = v0 + r;
    const int64_t i = v / (GY * GZ), j = (v / GZ) % GY, k = v % GZ;
    const T* a = txy + (i * GY + j) * H;
    const T* b = txz + (i * GZ + k) * H;
    const T* c = tyz + (j * GZ + k) * H;
    T* o = h + r * H;
    for (int64_t u = 0; u < H; ++u) o[u] = a[u] + b[u] + c[u];
  }
}

template <typename T>
void forward_grid(const Problem& p, at::Tensor& out, bool argmax) {
  const int64_t H0 = p.widths[1], C = p.C, L = p.layers();
  const at::Tensor w0c = p.weights[0].narrow(1, 0, C);  // [H0, C]
  const auto tx = axis_taps<T>(p.GX, p.PX), ty = axis_taps<T>(p.GY, p.PY),
             tz = axis_taps<T>(p.GZ, p.PZ);
  const at::Tensor ex = axis_encoding_contribution<T>(p, 0, p.GX);
  const at::Tensor ey = axis_encoding_contribution<T>(p, 1, p.GY);
  const at::Tensor ez = axis_encoding_contribution<T>(p, 2, p.GZ);
  const auto opts = p.xy.options();

  for (int64_t b = 0; b < p.B; ++b) {
    // Project each plane through the feature columns of W0 first (lookup is linear).
    const at::Tensor pxy = at::mm(p.xy[b].reshape({-1, C}), w0c.t());
    const at::Tensor pxz = at::mm(p.xz[b].reshape({-1, C}), w0c.t());
    const at::Tensor pyz = at::mm(p.yz[b].reshape({-1, C}), w0c.t());
    const at::Tensor txy = sample_table<T>(pxy, p.PY, tx, ty, ex.data_ptr<T>(),
                                           ey.data_ptr<T>(), p.biases[0].data_ptr<T>());
    const at::Tensor txz = sample_table<T>(pxz, p.PZ, tx, tz, nullptr, ez.data_ptr<T>(), nullptr);
    const at::Tensor tyz = sample_table<T>(pyz, p.PZ, ty, tz, nullptr, nullptr, nullptr);
    const T* Txy = txy.data_ptr<T>();
    const T* Txz = txz.data_ptr<T>();
    const T* Tyz = tyz.data_ptr<T>();

    const int64_t chunks = (p.per_batch + kChunk - 1) / kChunk;
    at::parallel_for(0, chunks, 1, [&](int64_t begin, int64_t end) {
      at::Tensor ping = at::empty({kChunk * p.max_width()}, opts);
      at::Tensor pong = at::empty({kChunk * p.max_width()}, opts);
      for (int64_t c = begin; c < end; ++c) {
        const int64_t v0 = c * kChunk, rows = std::min(kChunk, p.per_batch - v0);
        const int64_t start = b * p.per_batch + v0;
        // First layer from the tables; written straight to the output when it is the last.
        at::Tensor h0 = (L == 1 && !argmax) ? out.view({-1, H0}).narrow(0, start, rows)
                                             : view2d(ping, rows, H0);
        T* h = h0.data_ptr<T>();
        sum_tables(h, v0, rows, Txy, Txz, Tyz, p.GY, p.GZ, H0);
        if (L > 1) relu_inplace(h, rows * H0);
        at::Tensor logits = run_layers<T>(p, 1, h0, ping, pong, out, start, argmax);
        if (argmax) emit<T>(logits, out, start, true);
      }
    });
  }
}

at::Tensor triplane_decode_cpu(const at::Tensor& xy, const at::Tensor& xz, const at::Tensor& yz,
                               at::TensorList weights, at::TensorList biases,
                               const c10::optional<at::Tensor>& points,
                               c10::OptionalIntArrayRef grid, int64_t pe_freqs, bool argmax,
                               const c10::optional<at::Tensor>& live) {
  // The kernel uses ATen ops internally; they must not record autograd history.
  at::AutoDispatchBelowADInplaceOrView guard;
  const Problem p = make_problem(
      parse_triplane_args(xy, xz, yz, weights, biases, points, grid, pe_freqs, argmax, kOp), xy,
      xz, yz, weights, biases, points);
  check_live(live, p, argmax, xy, kOp);
  at::Tensor out = p.empty_output(xy, argmax);
  if (out.numel() == 0) return out;
  const at::Tensor counts = live.has_value() ? live->contiguous() : at::Tensor();
  if (counts.defined()) out.zero_();  // the labels of the points not decoded
  AT_DISPATCH_FLOATING_TYPES(xy.scalar_type(), "triplane_decode_cpu", [&] {
    if (p.grid_mode) {
      forward_grid<scalar_t>(p, out, argmax);
    } else {
      forward_features<scalar_t>(p, out, argmax, counts.defined() ? counts.data_ptr<int64_t>() : nullptr);
    }
  });
  return out;
}

// Per-thread gradient accumulators, summed at the end (no atomics, no locks).
struct Grads {
  at::Tensor xy, xz, yz;  // channels-last, like Problem's planes
  std::vector<at::Tensor> weights, biases;

  explicit Grads(const Problem& p) {
    xy = at::zeros_like(p.xy);
    xz = at::zeros_like(p.xz);
    yz = at::zeros_like(p.yz);
    for (int64_t l = 0; l < p.layers(); ++l) {
      weights.push_back(at::zeros_like(p.weights[l]));
      biases.push_back(at::zeros_like(p.biases[l]));
    }
  }
  void add(const Grads& o) {
    xy.add_(o.xy);
    xz.add_(o.xz);
    yz.add_(o.yz);
    for (size_t l = 0; l < weights.size(); ++l) {
      weights[l].add_(o.weights[l]);
      biases[l].add_(o.biases[l]);
    }
  }
};

// Scatters the feature gradients gf [count, C] of queries [start, start + count) into the
// three (channels-last) plane gradients.
template <typename T>
T3FAST_SIMD_CLONES void scatter_features(const Problem& p, int64_t start, int64_t count, const T* gf, Grads& g) {
  T* gxy = g.xy.data_ptr<T>();
  T* gxz = g.xz.data_ptr<T>();
  T* gyz = g.yz.data_ptr<T>();
  const T* pts = p.points.defined() ? p.points.data_ptr<T>() : nullptr;
  for (int64_t r = 0; r < count; ++r) {
    const int64_t n = start + r;
    const int64_t b = n / p.per_batch;
    T x, y, z;
    query_coords(p, pts, n, x, y, z);
    const Tap<T> tx = make_tap(x, p.PX), ty = make_tap(y, p.PY), tz = make_tap(z, p.PZ);
    const T* row = gf + r * p.C;
    scatter(gxy + b * p.PX * p.PY * p.C, p.PY, p.C, tx, ty, row);
    scatter(gxz + b * p.PX * p.PZ * p.C, p.PZ, p.C, tx, tz, row);
    scatter(gyz + b * p.PY * p.PZ * p.C, p.PZ, p.C, ty, tz, row);
  }
}

// Backward of one chunk: recompute its activations, then backpropagate layer by layer.
template <typename T>
void backward_chunk(const Problem& p, const at::Tensor& grad_rows, int64_t start,
                    std::vector<at::Tensor>& acts, at::Tensor& ping, at::Tensor& pong,
                    Grads& g) {
  const int64_t rows = grad_rows.size(0), L = p.layers();
  // acts[l] holds the input of layer l: acts[0] = features, acts[l] = ReLU output of l - 1.
  at::Tensor a0 = view2d(acts[0], rows, p.widths[0]);
  fill_features<T>(p, start, rows, a0.data_ptr<T>());
  std::vector<at::Tensor> in{a0};
  for (int64_t l = 1; l < L; ++l) {
    at::Tensor a = view2d(acts[l], rows, p.widths[l]);
    at::addmm_out(a, p.biases[l - 1], in.back(), p.weights[l - 1].t());
    relu_inplace(a.data_ptr<T>(), rows * p.widths[l]);
    in.push_back(a);
  }
  at::Tensor grad = grad_rows;  // gradient of layer l's output
  for (int64_t l = L - 1; l >= 0; --l) {
    g.weights[l].addmm_(grad.t(), in[l]);
    g.biases[l].add_(grad.sum(0));
    if (l == 0) break;
    at::Tensor next = view2d(grad.data_ptr() == ping.data_ptr() ? pong : ping, rows,
                             p.widths[l]);
    at::mm_out(next, grad, p.weights[l]);
    relu_backward(next.data_ptr<T>(), in[l].data_ptr<T>(), rows * p.widths[l]);
    grad = next;
  }
  // Only the plane features (the first C inputs) have a gradient; PE is constant.
  at::Tensor gf = view2d(grad.data_ptr() == ping.data_ptr() ? pong : ping, rows, p.C);
  at::mm_out(gf, grad, p.weights[0].narrow(1, 0, p.C));
  scatter_features<T>(p, start, rows, gf.data_ptr<T>(), g);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, std::vector<at::Tensor>, std::vector<at::Tensor>>
triplane_decode_backward_cpu(const at::Tensor& grad_out, const at::Tensor& xy,
                             const at::Tensor& xz, const at::Tensor& yz, at::TensorList weights,
                             at::TensorList biases, const c10::optional<at::Tensor>& points,
                             c10::OptionalIntArrayRef grid, int64_t pe_freqs) {
  // The kernel uses ATen ops internally; they must not record autograd history.
  at::AutoDispatchBelowADInplaceOrView guard;
  const Problem p = make_problem(parse_triplane_backward_args(grad_out, xy, xz, yz, weights,
                                                              biases, points, grid, pe_freqs,
                                                              kOpBwd),
                                 xy, xz, yz, weights, biases, points);
  const at::Tensor go = grad_out.detach().contiguous().view({-1, p.classes()});
  const int64_t total = go.size(0);
  const int64_t chunks = (total + kChunk - 1) / kChunk;
  std::vector<Grads> partial;
  for (int64_t t = 0; t < at::get_num_threads(); ++t) partial.emplace_back(p);
  const auto opts = p.xy.options();
  AT_DISPATCH_FLOATING_TYPES(xy.scalar_type(), "triplane_decode_backward_cpu", [&] {
    at::parallel_for(0, chunks, 1, [&](int64_t begin, int64_t end) {
      const auto tid = static_cast<size_t>(at::get_thread_num());
      TORCH_INTERNAL_ASSERT(tid < partial.size());
      Grads& g = partial[tid];
      std::vector<at::Tensor> acts;
      for (int64_t l = 0; l < p.layers(); ++l) {
        acts.push_back(at::empty({kChunk * p.widths[l]}, opts));
      }
      at::Tensor ping = at::empty({kChunk * p.max_width()}, opts);
      at::Tensor pong = at::empty({kChunk * p.max_width()}, opts);
      for (int64_t c = begin; c < end; ++c) {
        const int64_t start = c * kChunk, rows = std::min(kChunk, total - start);
        backward_chunk<scalar_t>(p, go.narrow(0, start, rows), start, acts, ping, pong, g);
      }
    });
  });
  for (size_t t = 1; t < partial.size(); ++t) partial[0].add(partial[t]);
  const Grads& g = partial[0];
  auto to_planar = [](const at::Tensor& cl) { return cl.permute({0, 3, 1, 2}).contiguous(); };
  return {to_planar(g.xy), to_planar(g.xz), to_planar(g.yz), g.weights, g.biases};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("triplane_decode", &triplane_decode_cpu);
  m.impl("triplane_decode_backward", &triplane_decode_backward_cpu);
}

}  // namespace t3fast
