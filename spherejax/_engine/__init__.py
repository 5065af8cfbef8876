"""How `spherejax.correct` runs, as opposed to what it computes (`spherejax.equations`).

Private: nothing here is public API, and names may move between releases.

- `kernels`: the kernel contract. What a per-pixel kernel computes and supports, its three
  implementations (the jax.numpy definition, the fused CPU kernel, the Pallas GPU kernel), and
  `choose`, the one place a kernel is picked, when a plan is made.
- `plan`: the prepared correction of one calibration and frame shape (`spherejax.plan` is its
  public face): constants cast once on the device the computation runs on, the kernel, the route
  its calls take (decided when it is made), and the compiled executables.
- `registered`: the correction of a calibration with band maps: the bands resampled into the
  reference geometry (`spherejax.band_resampling`), then the registered calibration's own plan;
  `fused_registration`: that resampling on CPU as a compiled custom call (kernel/register_bands.cc);
  concrete frames on CPU are registered inside the fused kernel's own loop instead
  (kernel/registered_rows.cc, `fused.correct_arrays(registration=...)`).
- `steps`: the jitted steps (the patch ratio, the per-pixel step with the plan's kernel, both as
  one program, and that program writing into donated outputs).
- `fused`: the fused CPU kernel's calls, from XLA (custom call, batching rule, JVP) and directly
  on NumPy frames; `fused_extension`: loading the compiled extension (sources in `kernel/`, whose
  `fused_correct.h` says which file does what) and registering it with XLA; `fused_variants`:
  which instruction-set variant runs (SPHEREJAX_FUSED and the measured choice); `variant_cache`:
  that measurement kept per machine; `fused_constants`: the calibration's arrays as the kernel
  takes them.
- `gpu_kernel`: the Pallas (Triton) kernel for NVIDIA GPUs; `gpu_residual`: its kernel residual.
- `buffers`: reuse of dropped outputs' and staged inputs' memory on CPU.
- `allocator`: glibc settings that keep freed memory for the next image.
"""
