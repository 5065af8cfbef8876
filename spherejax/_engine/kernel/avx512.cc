// The AVX-512 variant of the kernel: 16 bands (the instrument's), the generic block of
// fused_correct.h with a Stage II written with AVX-512 intrinsics.

#include "fused_correct.h"

#if SPHEREJAX_X86

#include <immintrin.h>

#include <type_traits>

namespace spherejax_fused {
namespace {

// Stage II (fused_correct.h) for 16 bands on AVX-512: one register a quantity, the flags as mask
// registers. Written with intrinsics because GCC turns vector-extension comparisons into scalar
// code (measured: the generic loop took 2x longer per pixel).
struct Avx512Stage2 {
  static constexpr int64_t kBands = kLanes;

  template <typename Raw>
  SPHEREJAX_AVX512_TARGET static inline uint8_t run(const Problem& pr, const Raw* r, const float* d,
                                                    const float* w, const float* a, const float* c,
                                                    float* tilde) {
    __m512 value;
    if constexpr (std::is_same_v<Raw, uint16_t>) {
      const __m256i counts = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(r));
      value = _mm512_cvtepi32_ps(_mm512_cvtepu16_epi32(counts));
    } else {
      value = _mm512_loadu_ps(r);
    }
    const __m512 zero = _mm512_setzero_ps();
    const __m512 dark = _mm512_loadu_ps(d);
    const __m512 signal = _mm512_sub_ps(_mm512_loadu_ps(w), dark);
    // x - x == 0 exactly when x is finite.
    const __mmask16 value_finite = _mm512_cmp_ps_mask(_mm512_sub_ps(value, value), zero, _CMP_EQ_OQ);
    const __mmask16 saturated =
        _mm512_mask_cmp_ps_mask(value_finite, value, _mm512_set1_ps(pr.saturation), _CMP_GE_OQ);
    const __mmask16 flat_field_ok =
        _mm512_cmp_ps_mask(signal, zero, _CMP_GT_OQ) &
        _mm512_cmp_ps_mask(_mm512_sub_ps(signal, signal), zero, _CMP_EQ_OQ);
    const __m512 v = _mm512_div_ps(_mm512_sub_ps(value, dark), signal);
    const __mmask16 below_dark =
        _mm512_mask_cmp_ps_mask(flat_field_ok & value_finite, v, _mm512_set1_ps(-kBelowDarkLimit), _CMP_LT_OQ);
    _mm512_store_ps(tilde, _mm512_fmadd_ps(_mm512_loadu_ps(a), v, _mm512_loadu_ps(c)));
    return static_cast<uint8_t>((saturated != 0) | ((value_finite != 0xFFFF) << 1) |
                                ((flat_field_ok != 0xFFFF) << 2) | ((below_dark != 0) << 4));
  }
};

}  // namespace

// flatten: inline everything, Avx512Stage2::run included, which the always_inline chain cannot
// (a default-target function may not inline an AVX-512 one).
SPHEREJAX_AVX512_TARGET __attribute__((flatten)) void correct_range_avx512(const Problem& pr, int64_t first,
                                                                           int64_t last) {
  correct_blocks<PixelByPixel<Avx512Stage2>>(pr, first, last);
}

}  // namespace spherejax_fused

#endif  // SPHEREJAX_X86
