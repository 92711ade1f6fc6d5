// The emulator's runtime: CUDA's execution model on the host, for testing kernels on a
// machine without a GPU.
//
// A launch runs its blocks one after another. A block's threads are fibers on one host thread,
// each with its own stack; a fiber runs until it reaches a barrier
// (__syncthreads, __syncthreads_or, __syncwarp) or returns, then the next one runs: in thread
// order in one block, last to first in the next (counting the blocks a host thread runs), so
// that a thread reading another thread's write with no barrier between them runs before the
// writer in one of the two orders, and reads the value unwritten. A
// barrier opens when every live thread of its scope (the block, or the warp) waits at it; a
// block whose threads wait at barriers that can never open (divergent barriers) fails the
// launch, as does any misuse the emulator checks (see emu_fail). Blocks share nothing but
// global memory, so running them in order shows the same results as a GPU gives for
// race-free kernels. Shared memory: `__shared__` variables are function statics (one copy,
// shared by the block's fibers; blocks run one at a time); the dynamic buffer has exactly the
// launch's size, is filled with garbage before every block (a kernel must not read what it
// did not write) and is followed by guard bytes that are checked after the block. Asynchronous
// copies to shared memory (cuda_pipeline.h) land only when their thread waits for them.
#pragma once

#include <math.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

struct dim3 {
  unsigned x = 1, y = 1, z = 1;
  dim3() = default;
  dim3(unsigned x_, unsigned y_ = 1, unsigned z_ = 1) : x(x_), y(y_), z(z_) {}
};

// Switches fibers (x86-64, defined in harness.cpp): pushes the callee-saved registers and the
// floating-point control words onto the running stack, stores its pointer in *save and pops
// the same from the stack `load`. A switch is a few nanoseconds; ucontext's swapcontext makes
// a signal-mask system call at every switch, which took most of an emulated forecast's time.
extern "C" void t3emu_switch(void** save, void* load);

namespace t3emu {

// The CUDA error codes the emulator returns (cuda_runtime.h names them).
constexpr int kSuccess = 0;
constexpr int kInvalidValue = 1;
constexpr int kInvalidConfiguration = 9;
constexpr int kLaunchFailure = 719;

enum class Wait { kNone, kBlock, kWarp, kDone };

// One asynchronous copy to shared memory: its source read when issued, written to `dst` when
// the issuing thread waits for its group.
struct AsyncCopy {
  unsigned char* dst;
  unsigned char bytes[16];
  size_t size;
};

struct Fiber {
  void* sp = nullptr;  // its saved stack (t3emu_switch)
  std::unique_ptr<char[]> stack;
  dim3 thread_idx;
  unsigned linear = 0;  // x fastest, as CUDA numbers the threads of a block
  Wait wait = Wait::kNone;
  int vote = 0;         // this thread's operand of a voting barrier
  int result = 0;       // the vote's result, once the barrier opens
  uint64_t posted = 0;  // this lane's value in a warp exchange (shuffle, ballot)
  std::vector<AsyncCopy> uncommitted;           // copies issued since the last commit
  std::deque<std::vector<AsyncCopy>> in_flight;  // committed groups, oldest first
};

struct BlockState {
  dim3 block_idx, block_dim, grid_dim;
  std::vector<Fiber> fibers;
  void* scheduler = nullptr;  // the launching thread's saved stack
  Fiber* current = nullptr;
  unsigned char* smem = nullptr;
  size_t smem_bytes = 0;
  const std::function<void()>* body = nullptr;
};

inline BlockState*& block_state() {
  static thread_local BlockState* state = nullptr;
  return state;
}

// The first error of the current launch (empty: none).
inline std::string& launch_error() {
  static thread_local std::string error;
  return error;
}

// Records a misuse of the CUDA model and ends the calling thread's fiber; the launch then
// fails with this message.
[[noreturn]] inline void emu_fail(const std::string& what) {
  if (launch_error().empty()) launch_error() = what;
  BlockState* b = block_state();
  if (b == nullptr || b->current == nullptr) {
    std::fprintf(stderr, "t3emu: %s\n", what.c_str());
    std::abort();
  }
  b->current->wait = Wait::kDone;
  t3emu_switch(&b->current->sp, b->scheduler);
  std::abort();  // a failed fiber is never resumed
}

inline const dim3& thread_idx() { return block_state()->current->thread_idx; }
inline const dim3& block_idx() { return block_state()->block_idx; }
inline const dim3& block_dim() { return block_state()->block_dim; }
inline const dim3& grid_dim() { return block_state()->grid_dim; }
inline unsigned char* dynamic_smem() { return block_state()->smem; }

// Warp intrinsics are emulated for whole warps only.
inline void require_full_warp(unsigned mask, const char* what) {
  if (mask != 0xffffffffu) emu_fail(std::string(what) + " with a partial mask is not emulated");
}

inline void wait_at(Wait w, int vote) {
  BlockState* b = block_state();
  b->current->wait = w;
  b->current->vote = vote;
  t3emu_switch(&b->current->sp, b->scheduler);
}

// A fiber's first function; a finished fiber is never resumed (the next block starts it anew).
[[noreturn]] inline void fiber_entry() {
  BlockState* b = block_state();
  (*b->body)();
  b->current->wait = Wait::kDone;
  t3emu_switch(&b->current->sp, b->scheduler);
  std::abort();
}

constexpr size_t kStackBytes = 256 * 1024;

// The launching thread's SSE and x87 control words (rounding, denormals), as t3emu_switch
// saves them, for a new fiber to start with.
inline uint64_t control_words() {
  uint32_t csr;
  uint16_t cw;
  asm volatile("stmxcsr %0" : "=m"(csr));
  asm volatile("fnstcw %0" : "=m"(cw));
  return csr | uint64_t{cw} << 32;
}

// Lays out a fresh stack as t3emu_switch leaves one, so that switching to it enters
// fiber_entry with the stack aligned as after a call.
inline void start_fiber(Fiber& f, uint64_t controls) {
  if (!f.stack) f.stack.reset(new char[kStackBytes]);
  auto* sp = reinterpret_cast<uint64_t*>(reinterpret_cast<uintptr_t>(f.stack.get() + kStackBytes) & ~uintptr_t{15});
  *--sp = 0;  // fiber_entry's return address: it never returns
  *--sp = reinterpret_cast<uint64_t>(&fiber_entry);
  for (int reg = 0; reg < 6; ++reg) *--sp = 0;  // rbp, rbx, r12-r15
  *--sp = controls;
  f.sp = sp;
}

constexpr size_t kGuardBytes = 4096;
constexpr unsigned char kGuard = 0xA5;

// Runs one block of `body` to completion; false (and launch_error set) when it failed.
inline bool run_block(BlockState& b) {
  const unsigned threads = b.block_dim.x * b.block_dim.y * b.block_dim.z;
  if (b.fibers.size() != threads) b.fibers = std::vector<Fiber>(threads);  // stacks kept across blocks
  const uint64_t controls = control_words();
  for (unsigned t = 0; t < threads; ++t) {
    Fiber& f = b.fibers[t];
    f.linear = t;
    f.thread_idx = dim3(t % b.block_dim.x, t / b.block_dim.x % b.block_dim.y,
                        t / (b.block_dim.x * b.block_dim.y));
    f.wait = Wait::kNone;
    f.uncommitted.clear();
    f.in_flight.clear();
    start_fiber(f, controls);
  }
  const unsigned warps = (threads + 31) / 32;
  // every other block runs its threads last to first (see the top of this file)
  static thread_local unsigned blocks_run = 0;
  const bool reverse = blocks_run++ % 2 == 1;
  while (true) {
    for (unsigned i = 0; i < threads; ++i) {
      Fiber& f = b.fibers[reverse ? threads - 1 - i : i];
      if (f.wait != Wait::kNone) continue;
      b.current = &f;
      t3emu_switch(&b.scheduler, f.sp);
      b.current = nullptr;
      if (!launch_error().empty()) return false;
    }
    bool released = false;
    for (unsigned w = 0; w < warps; ++w) {
      const unsigned lo = w * 32, hi = lo + 32 < threads ? lo + 32 : threads;
      bool any = false, all = true;
      for (unsigned t = lo; t < hi; ++t) {
        any |= b.fibers[t].wait == Wait::kWarp;
        all &= b.fibers[t].wait == Wait::kWarp || b.fibers[t].wait == Wait::kDone;
      }
      if (any && all) {
        for (unsigned t = lo; t < hi; ++t) {
          if (b.fibers[t].wait == Wait::kWarp) b.fibers[t].wait = Wait::kNone;
        }
        released = true;
      }
    }
    if (released) continue;
    bool any_block = false, all_block = true;
    int vote = 0;
    for (Fiber& f : b.fibers) {
      any_block |= f.wait == Wait::kBlock;
      all_block &= f.wait == Wait::kBlock || f.wait == Wait::kDone;
      if (f.wait == Wait::kBlock) vote |= f.vote;
    }
    if (!any_block) break;  // every thread returned
    if (!all_block) {
      launch_error() = "divergent barriers: some threads of a block wait at __syncthreads while "
                       "others wait at __syncwarp";
      return false;
    }
    for (Fiber& f : b.fibers) {
      if (f.wait == Wait::kBlock) {
        f.wait = Wait::kNone;
        f.result = vote;
      }
    }
  }
  return true;
}

// Kernels' dynamic shared memory limits set by cudaFuncSetAttribute.
inline std::map<const void*, int>& smem_limits() {
  static std::map<const void*, int> limits;
  return limits;
}

// The compute capability's major version the device reports (an H100's by default).
inline int& compute_capability_major() {
  static int major = 9;
  return major;
}

constexpr int kDefaultSmem = 48 * 1024;
constexpr int kOptinSmem = 227 * 1024;  // an H100's opt-in limit per block
constexpr int kSms = 132;

inline int& last_error() {
  static thread_local int err = kSuccess;
  return err;
}

// Runs a launch; returns 0 (cudaSuccess) or an error code, with launch_error() saying why.
inline int run_grid(const void* kernel, dim3 grid, dim3 block, size_t smem,
                    const std::function<void()>& body) {
  launch_error().clear();
  const unsigned threads = block.x * block.y * block.z;
  if (threads == 0 || threads > 1024 || grid.x == 0 || grid.y == 0 || grid.z == 0 ||
      grid.y > 65535 || grid.z > 65535) {
    launch_error() = "invalid launch configuration";
    return last_error() = kInvalidConfiguration;
  }
  auto limit = smem_limits().find(kernel);
  const size_t allowed = limit == smem_limits().end() ? kDefaultSmem : limit->second;
  if (smem > allowed) {
    launch_error() = "launch asks for " + std::to_string(smem) +
                     " bytes of dynamic shared memory, more than the kernel's limit " +
                     std::to_string(allowed) + " (cudaFuncSetAttribute)";
    return last_error() = kInvalidValue;
  }
  BlockState b;
  b.block_dim = block;
  b.grid_dim = grid;
  b.body = &body;
  std::unique_ptr<unsigned char[]> raw(new unsigned char[smem + kGuardBytes + 128]);
  unsigned char* aligned = reinterpret_cast<unsigned char*>(
      (reinterpret_cast<uintptr_t>(raw.get()) + 127) / 128 * 128);
  b.smem = aligned;
  b.smem_bytes = smem;
  BlockState* outer = block_state();
  block_state() = &b;
  int err = kSuccess;
  for (unsigned z = 0; z < grid.z && err == kSuccess; ++z) {
    for (unsigned y = 0; y < grid.y && err == kSuccess; ++y) {
      for (unsigned x = 0; x < grid.x && err == kSuccess; ++x) {
        b.block_idx = dim3(x, y, z);
        // garbage, as a GPU leaves it: a kernel must not read shared memory it did not write
        std::memset(aligned, 0x7F, smem);
        std::memset(aligned + smem, kGuard, kGuardBytes);
        if (!run_block(b)) {
          err = kLaunchFailure;
          break;
        }
        for (size_t i = 0; i < kGuardBytes; ++i) {
          if (aligned[smem + i] != kGuard) {
            launch_error() = "a block wrote past the end of its dynamic shared memory (" +
                             std::to_string(smem) + " bytes) at byte " +
                             std::to_string(smem + i);
            err = kLaunchFailure;
            break;
          }
        }
      }
    }
  }
  block_state() = outer;
  last_error() = err;
  return err;
}

// kernel<<<grid, block, smem, stream>>>(args...) is rewritten to
// t3emu::launch(kernel, grid, block, smem, stream)(args...).
template <typename Kernel>
auto launch(Kernel* kernel, dim3 grid, dim3 block, size_t smem = 0, void* stream = nullptr) {
  (void)stream;
  return [=](auto... args) {
    const std::function<void()> body = [&]() { kernel(args...); };
    run_grid(reinterpret_cast<const void*>(kernel), grid, block, smem, body);
  };
}

}  // namespace t3emu
