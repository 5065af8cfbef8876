// The generic variant of the kernel: the per-pixel code of fused_correct.h with the vector
// extension's 16-float Vec, for any band count. Every band count but 16 runs it under every
// variant, and 16 bands where it is asked for (SPHEREJAX_FUSED=generic) or where the CPU has
// neither AVX2 nor AVX-512.

#include "fused_correct.h"

namespace spherejax_fused {

// Compiled for three x86-64 levels and picked at load time (target_clones): the compiler's own
// vectorisation for AVX-512, AVX2 and baseline SSE2.
SPHEREJAX_CLONES void correct_range_generic(const Problem& pr, int64_t first, int64_t last) {
  correct_blocks<PixelByPixel<GenericStage2, GenericLanes>>(pr, first, last);
}

}  // namespace spherejax_fused
