"""How `spherejax.correct` runs, as opposed to what it computes (`spherejax.pipeline`).

Private: nothing here is public API, and names may move between releases.

- `plan`: the prepared correction of one calibration and frame shape (`spherejax.plan` is its
  public face): constants cast once, on the device the computation runs on, and the compiled
  executables of each route.
- `routes`: the ways through the per-pixel step (the fused CPU kernel called by XLA or directly
  on NumPy frames, the jax.numpy path in cache-sized blocks on CPU, whole images elsewhere,
  frames mapped with `jax.vmap`), each a function of a plan.
- `fused`: the Python side of the fused CPU kernel (`kernel/`, C++), and when it is used.
- `buffers`: reuse of dropped outputs' and staged inputs' memory on CPU.
- `allocator`: glibc settings that keep freed memory for the next image.
"""
