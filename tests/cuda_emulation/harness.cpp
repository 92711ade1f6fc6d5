// The emulated CUDA build's own pieces: the fiber switch (t3emu.h), the stream the glue asks
// for (the emulator has one, null) and the operators t3fast_emu_harness::selftest (the
// emulator's self-test kernels, selftest_kernel.cu) and ::set_compute_capability. They are
// torch operators rather than Python bindings: torch/library.h compiles in a fraction of
// torch/extension.h's time.
#include <ATen/ATen.h>
#include <torch/library.h>

#include <stdexcept>
#include <string>

#include "cuda/stream.h"

// t3emu_switch(void** save, void* load), System V x86-64: rdi = save, rsi = load. The saved
// frame, from the stack pointer up: MXCSR and the x87 control word (8 bytes), r15, r14, r13,
// r12, rbx, rbp, the return address (t3emu.h's start_fiber lays out a new fiber's alike).
asm(R"(
    .pushsection .text
    .globl t3emu_switch
    .type t3emu_switch, @function
t3emu_switch:
    pushq %rbp
    pushq %rbx
    pushq %r12
    pushq %r13
    pushq %r14
    pushq %r15
    subq $8, %rsp
    stmxcsr (%rsp)
    fnstcw 4(%rsp)
    movq %rsp, (%rdi)
    movq %rsi, %rsp
    ldmxcsr (%rsp)
    fldcw 4(%rsp)
    addq $8, %rsp
    popq %r15
    popq %r14
    popq %r13
    popq %r12
    popq %rbx
    popq %rbp
    ret
    .size t3emu_switch, .-t3emu_switch
    .popsection
)");

cudaError_t emulator_selftest(const std::string& name, const float* in, float* out, int blocks);

namespace t3fast {

cudaStream_t current_stream(int device_index) {
  (void)device_index;
  return nullptr;
}

}  // namespace t3fast

namespace {

// Runs one of selftest_kernel.cu's kernels on in (128 floats per block); returns out, or
// raises the launch's error.
at::Tensor selftest(c10::string_view name, const at::Tensor& in) {
  const at::Tensor x = in.to(at::kFloat).contiguous();
  at::Tensor out = at::zeros_like(x);
  const cudaError_t err = emulator_selftest(std::string(name), x.data_ptr<float>(),
                                            out.data_ptr<float>(), static_cast<int>(x.numel() / 128));
  if (err != cudaSuccess) {
    const std::string message = cudaGetErrorString(err);
    t3emu::launch_error().clear();
    throw std::runtime_error(message);
  }
  return out;
}

// The compute capability (major) the emulated device reports: below 8 the glue takes the
// CUDA-core kernels for every dtype, as on a GPU without bfloat16 tensor cores.
void set_compute_capability(int64_t major) {
  t3emu::compute_capability_major() = static_cast<int>(major);
}

}  // namespace

TORCH_LIBRARY(t3fast_emu_harness, m) {
  m.def("selftest(str name, Tensor input) -> Tensor", &selftest);
  m.def("set_compute_capability(int major) -> ()", &set_compute_capability);
}
