// CUDA's pipeline primitives (asynchronous copies from global to shared memory, cp.async on
// sm_80 and newer) on the emulator. A copy reads its source when issued and lands in shared
// memory only when the issuing thread waits for its group (__pipeline_wait_prior), so a kernel
// that reads a buffer before waiting for it, or before the barrier that makes the other
// threads' copies visible, reads the garbage the emulator left there.
#pragma once

#include <cstdint>
#include <cstring>
#include <string>
#include <utility>

#include "t3emu.h"

inline void __pipeline_memcpy_async(void* dst_shared, const void* src_global, size_t size_and_align,
                                    size_t zfill = 0) {
  using namespace ::t3emu;
  if (size_and_align != 4 && size_and_align != 8 && size_and_align != 16) {
    emu_fail("__pipeline_memcpy_async of " + std::to_string(size_and_align) + " bytes (4, 8 or 16)");
  }
  if (zfill > size_and_align) emu_fail("__pipeline_memcpy_async: zfill larger than the copy");
  const uintptr_t dst = reinterpret_cast<uintptr_t>(dst_shared);
  const uintptr_t src = reinterpret_cast<uintptr_t>(src_global);
  if (dst % size_and_align != 0 || src % size_and_align != 0) {
    emu_fail("__pipeline_memcpy_async of " + std::to_string(size_and_align) +
             " bytes with a source or destination not aligned to its size");
  }
  BlockState* b = block_state();
  const uintptr_t smem = reinterpret_cast<uintptr_t>(b->smem);
  if (dst < smem || dst + size_and_align > smem + b->smem_bytes) {
    emu_fail("__pipeline_memcpy_async to an address outside the dynamic shared memory");
  }
  AsyncCopy copy;
  copy.dst = static_cast<unsigned char*>(dst_shared);
  copy.size = size_and_align;
  std::memset(copy.bytes, 0, sizeof(copy.bytes));  // the last zfill bytes are zeros
  std::memcpy(copy.bytes, src_global, size_and_align - zfill);
  b->current->uncommitted.push_back(copy);
}

inline void __pipeline_commit() {
  ::t3emu::Fiber* self = ::t3emu::block_state()->current;
  self->in_flight.push_back(std::move(self->uncommitted));
  self->uncommitted.clear();
}

// Lands every committed group of the calling thread but the newest `prior`.
inline void __pipeline_wait_prior(size_t prior) {
  ::t3emu::Fiber* self = ::t3emu::block_state()->current;
  while (self->in_flight.size() > prior) {
    for (const ::t3emu::AsyncCopy& copy : self->in_flight.front()) {
      std::memcpy(copy.dst, copy.bytes, copy.size);
    }
    self->in_flight.pop_front();
  }
}
