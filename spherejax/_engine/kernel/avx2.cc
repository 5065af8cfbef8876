// The AVX2 + FMA variant of the kernel: 16 bands (the instrument's) on x86-64-v3 CPUs, written
// with intrinsics, in a block shape of its own (correct_block_avx2_16), and the kernel residual by
// the shared template (fused_correct.h, residual_of) with a lane policy of 8 floats (Avx2Lanes).
// Why: the generic code, compiled for this target, keeps its 16-float vectors as pairs of ymm
// registers that GCC spills to the stack around every FMA (measured: 4x slower than the jax.numpy
// path on a 2-core AVX2 EPYC). The same equations; the sums run in another order than the generic
// code's (see affine_block_avx2_16) and its exponential rounds differently (Avx2Lanes::exp), so
// its bits may differ from the other variants' in the last place (spherejax._engine.fused keeps
// one variant per process for that reason).

#include "fused_correct.h"

#if SPHEREJAX_X86

#include <immintrin.h>

#include <type_traits>

namespace spherejax_fused {
namespace {

// Stage II (fused_correct.h) for 16 bands on AVX2 + FMA.
struct Avx2Stage2 {
  static constexpr int64_t kBands = kLanes;

  template <typename Raw>
  SPHEREJAX_AVX2_TARGET static inline uint8_t run(const Problem& pr, const Raw* r, const float* d, const float* w,
                                                  const float* a, const float* c, float* tilde) {
    const __m256 zero = _mm256_setzero_ps();
    const __m256 saturation = _mm256_set1_ps(pr.saturation);
    const __m256 infinity = _mm256_set1_ps(INFINITY);
    // The flags of both halves as lane masks, turned into bits once.
    __m256 saturated = zero, value_finite = _mm256_cmp_ps(zero, zero, _CMP_EQ_OQ), flat_field_ok = value_finite;
    __m256 below_dark = zero;
    for (int half = 0; half < 2; ++half) {
      const int64_t o = 8 * half;
      __m256 value, finite = _mm256_cmp_ps(zero, zero, _CMP_EQ_OQ);  // lanes of finite raw values
      if constexpr (std::is_same_v<Raw, uint16_t>) {
        const __m128i counts = _mm_loadu_si128(reinterpret_cast<const __m128i*>(r + o));
        value = _mm256_cvtepi32_ps(_mm256_cvtepu16_epi32(counts));
        // A count is finite: no check.
        saturated = _mm256_or_ps(saturated, _mm256_cmp_ps(value, saturation, _CMP_GE_OQ));
      } else {
        value = _mm256_loadu_ps(r + o);
        // x - x == 0 exactly when x is finite.
        finite = _mm256_cmp_ps(_mm256_sub_ps(value, value), zero, _CMP_EQ_OQ);
        value_finite = _mm256_and_ps(value_finite, finite);
        saturated = _mm256_or_ps(saturated, _mm256_and_ps(finite, _mm256_cmp_ps(value, saturation, _CMP_GE_OQ)));
      }
      const __m256 dark = _mm256_loadu_ps(d + o);
      const __m256 signal = _mm256_sub_ps(_mm256_loadu_ps(w + o), dark);
      // 0 < signal < inf: positive and finite (NaN fails both).
      const __m256 band_ok = _mm256_and_ps(_mm256_cmp_ps(signal, zero, _CMP_GT_OQ), _mm256_cmp_ps(signal, infinity, _CMP_LT_OQ));
      flat_field_ok = _mm256_and_ps(flat_field_ok, band_ok);
      const __m256 v = _mm256_div_ps(_mm256_sub_ps(value, dark), signal);
      below_dark = _mm256_or_ps(below_dark, _mm256_and_ps(_mm256_and_ps(band_ok, finite),
                                                           _mm256_cmp_ps(v, _mm256_set1_ps(-kBelowDarkLimit), _CMP_LT_OQ)));
      _mm256_store_ps(tilde + o, _mm256_fmadd_ps(_mm256_loadu_ps(a + o), v, _mm256_loadu_ps(c + o)));
    }
    return static_cast<uint8_t>((_mm256_movemask_ps(saturated) != 0) | ((_mm256_movemask_ps(value_finite) != 0xFF) << 1) |
                                ((_mm256_movemask_ps(flat_field_ok) != 0xFF) << 2) |
                                ((_mm256_movemask_ps(below_dark) != 0) << 4));
  }
};

// lab_f of N vectors of 8 values, without a division: the cube root of x as x y^2, where y = x^(-1/3) comes
// from an exponent-dividing first guess (within 3.5 %: magic - bits / 3, the bits divided in
// float, exact enough for a guess) and two Newton steps y <- y (4 - x y^3) / 3, then one Newton
// step on the root itself, c <- c + (x - c^3) y^2 / 3 (y^2 ~ 1 / c^2). Within 1 ulp of the
// correctly rounded cube root over Lab's range (checked against float64 in
// tests/test_fused.py). The scalar `lab_f` (fused_correct.h) divides (two Halley steps); this
// takes products only, which pipeline where divisions do not.
//
// N vectors at a time, each step written for all of them before the next: the steps of one
// vector depend on each other (about 20 operations in a row), so it takes several vectors side
// by side to keep the FMA units busy (measured: six vectors, 16 pixels' X, Y and Z, against
// three: 65 -> 63 ns a pixel in all, one thread of a Zen 1 EPYC).
template <int N>
SPHEREJAX_AVX2_TARGET inline void lab_f_avx2(__m256 (&t)[N]) {
  const __m256 third = _mm256_set1_ps(1.0f / 3.0f), four = _mm256_set1_ps(4.0f);
  __m256 above[N], x[N], y[N], y2[N], root[N];
  for (int k = 0; k < N; ++k) {
    above[k] = _mm256_cmp_ps(t[k], _mm256_set1_ps(kLabEpsilon), _CMP_GT_OQ);
    x[k] = _mm256_blendv_ps(_mm256_set1_ps(1.0f), t[k], above[k]);
    const __m256i bits_third = _mm256_cvtps_epi32(_mm256_mul_ps(_mm256_cvtepi32_ps(_mm256_castps_si256(x[k])), third));
    y[k] = _mm256_castsi256_ps(_mm256_sub_epi32(_mm256_set1_epi32(0x54a232a0), bits_third));
  }
  for (int step = 0; step < 2; ++step) {
    for (int k = 0; k < N; ++k) {
      // x y^3 as (x y) y^2: two products side by side, not three in a row.
      const __m256 reduced = _mm256_fnmadd_ps(_mm256_mul_ps(x[k], y[k]), _mm256_mul_ps(y[k], y[k]), four);
      y[k] = _mm256_mul_ps(_mm256_mul_ps(y[k], third), reduced);
    }
  }
  for (int k = 0; k < N; ++k) {
    y2[k] = _mm256_mul_ps(y[k], y[k]);
    root[k] = _mm256_mul_ps(x[k], y2[k]);
  }
  for (int k = 0; k < N; ++k) {
    const __m256 residual = _mm256_fnmadd_ps(_mm256_mul_ps(root[k], root[k]), root[k], x[k]);
    root[k] = _mm256_fmadd_ps(_mm256_mul_ps(residual, y2[k]), third, root[k]);
    const __m256 linear = _mm256_fmadd_ps(_mm256_set1_ps(kLabKappa / 116.0f), t[k], _mm256_set1_ps(16.0f / 116.0f));
    t[k] = _mm256_blendv_ps(linear, root[k], above[k]);
  }
}

// A value the compiler must keep in a register, not fold into the instructions that use it:
// for a matrix row loaded once and shared by two FMAs, which GCC otherwise turns into two FMAs
// with a memory operand each, loading the row twice and undoing the sharing (measured: the
// loads then bound the projection).
template <typename V>
SPHEREJAX_AVX2_TARGET inline V in_register(V v) {
  __asm__("" : "+x"(v));
  return v;
}

// Lane 7 of a ymm register as a scalar.
SPHEREJAX_AVX2_TARGET inline float lane7(__m256 v) {
  return _mm_cvtss_f32(_mm_permute_ps(_mm256_extractf128_ps(v, 1), 3));
}

// The 8 x 8 floats at rows[k * stride] (k < 8, each row 32-byte aligned) transposed into out[8]:
// interleaves of 32 and 64 bits within 128-bit lanes, then 128-bit lane swaps (24 instructions).
SPHEREJAX_AVX2_TARGET inline void transpose_8(const float* rows, int64_t stride, __m256* out) {
  __m256 t[8], u[8];
  for (int k = 0; k < 4; ++k) {
    const __m256 a = _mm256_load_ps(rows + 2 * k * stride), b = _mm256_load_ps(rows + (2 * k + 1) * stride);
    t[2 * k] = _mm256_unpacklo_ps(a, b);      // a0 b0 a1 b1 | a4 b4 a5 b5
    t[2 * k + 1] = _mm256_unpackhi_ps(a, b);  // a2 b2 a3 b3 | a6 b6 a7 b7
  }
  for (int k = 0; k < 2; ++k) {
    const __m256 lo0 = t[4 * k], hi0 = t[4 * k + 1], lo1 = t[4 * k + 2], hi1 = t[4 * k + 3];
    u[4 * k + 0] = _mm256_shuffle_ps(lo0, lo1, _MM_SHUFFLE(1, 0, 1, 0));  // column 0 | 4 of rows 4k..4k+3
    u[4 * k + 1] = _mm256_shuffle_ps(lo0, lo1, _MM_SHUFFLE(3, 2, 3, 2));  // column 1 | 5
    u[4 * k + 2] = _mm256_shuffle_ps(hi0, hi1, _MM_SHUFFLE(1, 0, 1, 0));  // column 2 | 6
    u[4 * k + 3] = _mm256_shuffle_ps(hi0, hi1, _MM_SHUFFLE(3, 2, 3, 2));  // column 3 | 7
  }
  for (int c = 0; c < 4; ++c) {
    out[c] = _mm256_permute2f128_ps(u[c], u[4 + c], 0x20);
    out[c + 4] = _mm256_permute2f128_ps(u[c], u[4 + c], 0x31);
  }
}

// 16 floats as two ymm registers: the kernel residual's vector (Avx2Lanes). Each operation with
// a scalar broadcasts it once for both halves. (GCC's own 16-float vector, Vec, compiled for AVX2
// goes through the stack; written out as a pair of registers it does not.)
struct Ymm2 {
  __m256 lo, hi;
};
SPHEREJAX_AVX2_TARGET inline Ymm2 operator+(Ymm2 a, Ymm2 b) {
  return {_mm256_add_ps(a.lo, b.lo), _mm256_add_ps(a.hi, b.hi)};
}
SPHEREJAX_AVX2_TARGET inline Ymm2 operator*(Ymm2 a, Ymm2 b) {
  return {_mm256_mul_ps(a.lo, b.lo), _mm256_mul_ps(a.hi, b.hi)};
}
SPHEREJAX_AVX2_TARGET inline Ymm2 operator+(Ymm2 a, float b) {
  const __m256 c = _mm256_set1_ps(b);
  return {_mm256_add_ps(a.lo, c), _mm256_add_ps(a.hi, c)};
}
SPHEREJAX_AVX2_TARGET inline Ymm2 operator*(Ymm2 a, float b) {
  const __m256 c = _mm256_set1_ps(b);
  return {_mm256_mul_ps(a.lo, c), _mm256_mul_ps(a.hi, c)};
}
SPHEREJAX_AVX2_TARGET inline Ymm2 operator*(float a, Ymm2 b) { return b * a; }
SPHEREJAX_AVX2_TARGET inline Ymm2 operator-(float a, Ymm2 b) {
  const __m256 c = _mm256_set1_ps(a);
  return {_mm256_sub_ps(c, b.lo), _mm256_sub_ps(c, b.hi)};
}
SPHEREJAX_AVX2_TARGET inline Ymm2& operator+=(Ymm2& a, Ymm2 b) { return a = a + b; }

// 2^min(t, 0) of 8 lanes (e^x with x log2(e) = t folded into the constants, fused_correct.h,
// Problem), with as few multiply-adds as exp2_nonpositive allows (measured: the exponentials take
// a sixth of the residual's time): t = n + f, n floored at -125 so
// that no result is subnormal, rounded to nearest by adding 1.5 x 2^23, which leaves n in the low
// bits of the sum; 2^f by a polynomial of degree 5 fitted for the least relative error on
// [-1/2, 1/2] (7.5e-8, 2.3e-7 evaluated in float32: as close as exp2_nonpositive's Taylor
// polynomial of degree 6); and 2^n added to its exponent bits as the integer n << 23, the sum's
// low bits shifted up (the bits above them shift out). min and max take the NaN-carrying operand
// second, which they return when either is NaN, and a NaN's shifted bits are 0: a NaN stays NaN.
//
// N vectors at a time, each step written for all of them before the next: one exponential is a
// chain of about 12 dependent operations (measured on a Zen 4, 200 inducing points: four side by
// side took an eighth less time than two).
template <int N>
SPHEREJAX_AVX2_TARGET inline void exp2_nonpositive_avx2(__m256* x) {
  const __m256 magic = _mm256_set1_ps(12582912.0f);
  __m256 t[N], shifted[N], f[N], p[N];
  for (int k = 0; k < N; ++k) {
    t[k] = _mm256_max_ps(_mm256_set1_ps(-125.0f), _mm256_min_ps(_mm256_setzero_ps(), x[k]));
  }
  for (int k = 0; k < N; ++k) shifted[k] = _mm256_add_ps(t[k], magic);
  for (int k = 0; k < N; ++k) f[k] = _mm256_sub_ps(t[k], _mm256_sub_ps(shifted[k], magic));
  for (int k = 0; k < N; ++k) {
    p[k] = _mm256_fmadd_ps(_mm256_set1_ps(1.327644451521337e-3f), f[k], _mm256_set1_ps(9.67553723603487e-3f));
  }
  for (int k = 0; k < N; ++k) p[k] = _mm256_fmadd_ps(p[k], f[k], _mm256_set1_ps(5.550713464617729e-2f));
  for (int k = 0; k < N; ++k) p[k] = _mm256_fmadd_ps(p[k], f[k], _mm256_set1_ps(2.4022120237350464e-1f));
  for (int k = 0; k < N; ++k) p[k] = _mm256_fmadd_ps(p[k], f[k], _mm256_set1_ps(6.931469440460205e-1f));
  for (int k = 0; k < N; ++k) p[k] = _mm256_fmadd_ps(p[k], f[k], _mm256_set1_ps(1.0000001192092896f));
  for (int k = 0; k < N; ++k) {
    const __m256i n_bits = _mm256_slli_epi32(_mm256_castps_si256(shifted[k]), 23);
    x[k] = _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(p[k]), n_bits));
  }
}

// The lane policy of the kernel residual (fused_correct.h, residual_of) on AVX2: 16 pixels a
// vector, as two ymm registers (Ymm2), so that every matrix element broadcast from memory feeds
// two multiply-adds; with one ymm a vector, the broadcasts as many as the multiply-adds, the
// residual took 15 % longer (measured on a Zen 4, 64 inducing points). Steps of 4: their 8
// accumulators, the two registers of v_tilde and a broadcast fit AVX2's 16 registers.
struct Avx2Lanes {
  using V = Ymm2;
  static constexpr int kWidth = 16;
  static constexpr int kWhiteningStep = 4, kInducingStep = 4, kRankStep = 4, kOutputStep = 4;

  SPHEREJAX_AVX2_TARGET static inline V load(const float* from) {
    return V{_mm256_load_ps(from), _mm256_load_ps(from + 8)};
  }
  SPHEREJAX_AVX2_TARGET static inline void store(float* to, V x) {
    _mm256_store_ps(to, x.lo), _mm256_store_ps(to + 8, x.hi);
  }

  // n is a multiple of kResidualRows: two vectors, four registers, at a time.
  SPHEREJAX_AVX2_TARGET static inline void exp2(V* k, int64_t n) {
    static_assert(kResidualRows % 2 == 0, "inducing points in pairs");
    for (int64_t j = 0; j < n; j += 2) {
      __m256 x[4] = {k[j].lo, k[j].hi, k[j + 1].lo, k[j + 1].hi};
      exp2_nonpositive_avx2<4>(x);
      k[j] = V{x[0], x[1]}, k[j + 1] = V{x[2], x[3]};
    }
  }

  // columns (fused_correct.h) for 16 bands: 8 x 8 tiles of the block transposed in registers.
  SPHEREJAX_AVX2_TARGET static inline void columns(const float (*rows)[kMaxBands], int64_t,
                                                   float (*columns)[kBlock]) {
    for (int64_t first = 0; first < kBlock; first += 8) {
      for (int64_t band = 0; band < kLanes; band += 8) {
        __m256 c[8];
        transpose_8(rows[first] + band, kMaxBands, c);
        for (int k = 0; k < 8; ++k) _mm256_store_ps(columns[band + k] + first, c[k]);
      }
    }
  }

  // write_rows (fused_correct.h) for all kBlock pixels (count is not read: `to` is a block's
  // buffer with room for them and one float beyond): 8 x 8 tiles of outputs transposed in
  // registers and stored as 8 floats per pixel. Tiles of outputs 24-31 write one float past
  // their pixel's 31 (output 31, X, into the next pixel's output 0), so they go first and the
  // tiles of outputs 0-7 overwrite those floats last.
  SPHEREJAX_AVX2_TARGET static inline void write_rows(const float (*out)[kBlock], int64_t, float* to) {
    for (int64_t o0 = 24; o0 >= 0; o0 -= 8) {
      for (int64_t first = 0; first < kBlock; first += 8) {
        __m256 c[8];
        transpose_8(out[o0] + first, kBlock, c);
        for (int k = 0; k < 8; ++k) _mm256_storeu_ps(to + (first + k) * kReflectance + o0, c[k]);
      }
    }
  }
};

// The affine block in two passes: quality and v_tilde of every pixel, then the projection, two
// pixels at a time, into the block's reflectance (a row of 31 floats per pixel) and XYZ
// (xyz[c][pixel]).
// (On a 2-core first-generation EPYC, whose ymm operations are two 128-bit halves: 83 -> 60-65
// ns a pixel on one thread, with finish_block_avx2, against the one-pixel loop with the Halley
// root, which this replaced.)
//
// The projection of a pixel is 16 broadcasts of its v_tilde times the matrix rows, into 34
// accumulator lanes: four ymm (reflectance 0..30, X) and one xmm (Y, Z, padding), 9 register
// FMAs a band where five ymm took 10. Two pixels share each row load (10 accumulators, 3
// temporaries: 13 of the 16 ymm registers), halving the loads, which bound the one-pixel loop
// (80 row loads and 16 broadcasts against 80 FMAs a pixel). Each accumulator starts at the bias
// (the estimator's offset): a zero bias gives the bits of a zero start. The sums' order depends
// only on the pixel, never on its partner or place in the block, so strips give the bits of the
// whole image.
template <typename Raw>
SPHEREJAX_AVX2_TARGET inline void affine_block_avx2_16(const Problem& pr, int64_t first, int64_t count,
                                                       float* reflectance, float (*xyz)[kBlock], uint8_t* quality) {
  constexpr int64_t B = kLanes;
  alignas(32) float tilde[kBlock][B];
  stage2_of_block<Raw, Avx2Stage2>(pr, first, count, tilde, quality);
  // Columns 0..35 of the (B, 48) matrix and bias: 31 reflectances, X, Y, Z, padding.
  const float* projection = reinterpret_cast<const float*>(pr.projection);
  const float* bias = reinterpret_cast<const float*>(pr.bias);
  for (int64_t i = 0; i < kBlock; i += 2) {
    __m256 a0 = _mm256_load_ps(bias), a1 = _mm256_load_ps(bias + 8), a2 = _mm256_load_ps(bias + 16),
           a3 = _mm256_load_ps(bias + 24);
    __m128 a4 = _mm_load_ps(bias + 32);
    __m256 b0 = a0, b1 = a1, b2 = a2, b3 = a3;
    __m128 b4 = a4;
#pragma GCC unroll 16
    for (int64_t b = 0; b < B; ++b) {
      const float* m = projection + b * kPadded;
      const __m256 s = _mm256_broadcast_ss(&tilde[i][b]), t = _mm256_broadcast_ss(&tilde[i + 1][b]);
      __m256 row = in_register(_mm256_load_ps(m));
      a0 = _mm256_fmadd_ps(s, row, a0), b0 = _mm256_fmadd_ps(t, row, b0);
      row = in_register(_mm256_load_ps(m + 8));
      a1 = _mm256_fmadd_ps(s, row, a1), b1 = _mm256_fmadd_ps(t, row, b1);
      row = in_register(_mm256_load_ps(m + 16));
      a2 = _mm256_fmadd_ps(s, row, a2), b2 = _mm256_fmadd_ps(t, row, b2);
      row = in_register(_mm256_load_ps(m + 24));
      a3 = _mm256_fmadd_ps(s, row, a3), b3 = _mm256_fmadd_ps(t, row, b3);
      const __m128 tail = in_register(_mm_load_ps(m + 32));
      a4 = _mm_fmadd_ps(_mm256_castps256_ps128(s), tail, a4);
      b4 = _mm_fmadd_ps(_mm256_castps256_ps128(t), tail, b4);
    }
    float* out = reflectance + i * kReflectance;
    _mm256_storeu_ps(out, a0), _mm256_storeu_ps(out + 8, a1), _mm256_storeu_ps(out + 16, a2);
    _mm256_storeu_ps(out + 24, a3);  // lane 7, X, is overwritten by the next pixel's first store
    _mm256_storeu_ps(out + kReflectance, b0), _mm256_storeu_ps(out + kReflectance + 8, b1);
    _mm256_storeu_ps(out + kReflectance + 16, b2), _mm256_storeu_ps(out + kReflectance + 24, b3);
    xyz[0][i] = lane7(a3), xyz[0][i + 1] = lane7(b3);
    xyz[1][i] = _mm_cvtss_f32(a4), xyz[1][i + 1] = _mm_cvtss_f32(b4);
    xyz[2][i] = _mm_cvtss_f32(_mm_movehdup_ps(a4)), xyz[2][i + 1] = _mm_cvtss_f32(_mm_movehdup_ps(b4));
  }
}

// The block with the kernel residual: quality and v_tilde of every pixel, turned into columns
// (Avx2Lanes::columns), then every output of 16 pixels at a time by the residual's template
// (residual_of with Avx2Lanes: the affine estimate and the residual), the reflectance turned back
// into rows (Avx2Lanes::write_rows). Its XYZ stay columns: out[31 + c].
template <typename Raw>
SPHEREJAX_AVX2_TARGET inline void residual_block_avx2_16(const Problem& pr, int64_t first, int64_t count,
                                                         float* reflectance, float (*out)[kBlock],
                                                         uint8_t* quality) {
  alignas(32) float rows[kBlock][kMaxBands];
  alignas(32) float tilde[kMaxBands][kBlock];
  stage2_of_block<Raw, Avx2Stage2>(pr, first, count, rows, quality);
  Avx2Lanes::columns(rows, kLanes, tilde);
  residual_of_block<Avx2Lanes>(pr, kLanes, tilde, out);
  Avx2Lanes::write_rows(out, kBlock, reflectance);
}

// Lab of a block's pixels from their XYZ (xyz[c][pixel]), sixteen at a time, and the block's
// outputs written: its reflectance (a row of 31 floats per pixel), Lab and quality.
//
// Stores: a block's reflectance (32 pixels x 31 floats = 124 whole ymm), Lab (12 ymm) and
// quality (one ymm) are contiguous and 32-byte aligned when the block starts at a multiple of 32
// pixels of an aligned buffer, so they are written with non-temporal stores: the outputs are
// written whole and never read back here, and ordinary stores would first read every cache line
// they overwrite (a read of 136 bytes a pixel that the path does not need). Other blocks (the
// last, partial one) take ordinary stores.
SPHEREJAX_AVX2_TARGET inline void finish_block_avx2(const Problem& pr, int64_t first, int64_t count,
                                                    float* reflectance, const float (*xyz)[kBlock],
                                                    uint8_t* quality) {
  alignas(32) float lab[kBlock * 3];
  for (int64_t i = 0; i < kBlock; i += 16) {
    // f(X / Xn), f(Y / Yn), f(Z / Zn) of pixels i..i+7 and i+8..i+15, side by side.
    __m256 f[6];
    for (int k = 0; k < 3; ++k) {
      const __m256 inverse_white = _mm256_set1_ps(pr.inverse_white[k]);
      f[2 * k] = _mm256_mul_ps(_mm256_load_ps(xyz[k] + i), inverse_white);
      f[2 * k + 1] = _mm256_mul_ps(_mm256_load_ps(xyz[k] + i + 8), inverse_white);
    }
    lab_f_avx2(f);
    for (int half = 0; half < 2; ++half) {
      const __m256 fx = f[half], fy = f[2 + half], fz = f[4 + half];
      const __m256 l = _mm256_fmsub_ps(_mm256_set1_ps(116.0f), fy, _mm256_set1_ps(16.0f));
      const __m256 a = _mm256_mul_ps(_mm256_set1_ps(500.0f), _mm256_sub_ps(fx, fy));
      const __m256 b = _mm256_mul_ps(_mm256_set1_ps(200.0f), _mm256_sub_ps(fy, fz));
      // Interleave to L a b L a b ... in each 128-bit lane (four of the eight pixels each): in-lane
      // shuffles only, which cost one operation a lane on every AVX2 CPU.
      const __m256 la_lo = _mm256_unpacklo_ps(l, a), la_hi = _mm256_unpackhi_ps(l, a);  // L0 a0 L1 a1 | L2 a2 L3 a3
      const __m256 bl_lo = _mm256_unpacklo_ps(b, l), bl_hi = _mm256_unpackhi_ps(b, l);  // b0 L0 b1 L1 | b2 L2 b3 L3
      const __m256 ab_lo = _mm256_unpacklo_ps(a, b), ab_hi = _mm256_unpackhi_ps(a, b);  // a0 b0 a1 b1 | a2 b2 a3 b3
      const __m256 first4 = _mm256_shuffle_ps(la_lo, bl_lo, _MM_SHUFFLE(3, 0, 1, 0));   // L0 a0 b0 L1
      const __m256 middle4 = _mm256_shuffle_ps(ab_lo, la_hi, _MM_SHUFFLE(1, 0, 3, 2));  // a1 b1 L2 a2
      const __m256 last4 = _mm256_shuffle_ps(bl_hi, ab_hi, _MM_SHUFFLE(3, 2, 3, 0));    // b2 L3 a3 b3
      float* out = lab + 3 * (i + 8 * half);
      _mm_store_ps(out, _mm256_castps256_ps128(first4));
      _mm_store_ps(out + 4, _mm256_castps256_ps128(middle4));
      _mm_store_ps(out + 8, _mm256_castps256_ps128(last4));
      _mm_store_ps(out + 12, _mm256_extractf128_ps(first4, 1));
      _mm_store_ps(out + 16, _mm256_extractf128_ps(middle4, 1));
      _mm_store_ps(out + 20, _mm256_extractf128_ps(last4, 1));
    }
  }
  // Good pixels whose outputs are not finite (fused_correct.h, flag_nonfinite_outputs): the sum of
  // the block's reflectance rows (in whole ymm: 124 for a full block) and XYZ in four accumulators,
  // about four additions a pixel; a sum that is not finite (a bad pixel's NaN, an output that is not
  // finite, or finite ones that overflow) sends the block through its good pixels one by one.
  {
    __m256 sums[4] = {_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps()};
    const int64_t whole = count * kReflectance / 8 * 8;
    int64_t k = 0;
    for (; k + 32 <= whole; k += 32) {
      for (int q = 0; q < 4; ++q) sums[q] = _mm256_add_ps(sums[q], _mm256_loadu_ps(reflectance + k + 8 * q));
    }
    for (; k < whole; k += 8) sums[0] = _mm256_add_ps(sums[0], _mm256_loadu_ps(reflectance + k));
    for (int c = 0; c < 3; ++c) {
      for (int64_t i = 0; i < kBlock; i += 8) sums[1 + c] = _mm256_add_ps(sums[1 + c], _mm256_load_ps(xyz[c] + i));
    }
    alignas(32) float lanes[8];
    _mm256_store_ps(lanes, _mm256_add_ps(_mm256_add_ps(sums[0], sums[1]), _mm256_add_ps(sums[2], sums[3])));
    float zero = 0.0f;
    for (int q = 0; q < 8; ++q) zero += lanes[q] * 0.0f;
    for (int64_t r = whole; r < count * kReflectance; ++r) zero += reflectance[r] * 0.0f;
    if (!(zero == 0.0f)) flag_nonfinite_outputs(count, reflectance, lab, 3, 1, quality);
  }
  float* reflectance_out = pr.reflectance + first * kReflectance;
  float* lab_out = pr.lab + first * 3;
  uint8_t* quality_out = pr.quality + first;
  const bool streamable = count == kBlock && (reinterpret_cast<uintptr_t>(reflectance_out) % 32 == 0) &&
                          (reinterpret_cast<uintptr_t>(lab_out) % 32 == 0) &&
                          (reinterpret_cast<uintptr_t>(quality_out) % 32 == 0);
  if (streamable) {
    for (int64_t k = 0; k < kBlock * kReflectance; k += 8) {
      _mm256_stream_ps(reflectance_out + k, _mm256_load_ps(reflectance + k));
    }
    for (int64_t k = 0; k < kBlock * 3; k += 8) _mm256_stream_ps(lab_out + k, _mm256_load_ps(lab + k));
    _mm256_stream_si256(reinterpret_cast<__m256i*>(quality_out), _mm256_load_si256(reinterpret_cast<const __m256i*>(quality)));
  } else {
    std::memcpy(reflectance_out, reflectance, count * kReflectance * sizeof(float));
    std::memcpy(lab_out, lab, count * 3 * sizeof(float));
    std::memcpy(quality_out, quality, count);
  }
}

// One block of 32 pixels: the affine block or the residual's, then Lab and the stores.
template <typename Raw>
SPHEREJAX_AVX2_TARGET inline void correct_block_avx2_16(const Problem& pr, int64_t first, int64_t count) {
  // Room beyond the block (one float is needed): pixel i's 32-float store spills its X into pixel
  // i + 1's first slot, which pixel i + 1 then overwrites; the last pixel's lands here.
  alignas(32) float reflectance[kBlock * kReflectance + 8];
  alignas(32) uint8_t quality[kBlock];
  if (pr.inducing_rows > 0) {
    alignas(32) float out[kPadded][kBlock];
    residual_block_avx2_16<Raw>(pr, first, count, reflectance, out, quality);
    finish_block_avx2(pr, first, count, reflectance, out + kReflectance, quality);
  } else {
    alignas(32) float xyz[3][kBlock];
    affine_block_avx2_16<Raw>(pr, first, count, reflectance, xyz, quality);
    finish_block_avx2(pr, first, count, reflectance, xyz, quality);
  }
}

// correct_block_avx2_16 as a Block type for correct_blocks.
struct Avx2Block {
  template <typename Raw>
  SPHEREJAX_AVX2_TARGET static inline void run(const Problem& pr, int64_t first, int64_t count) {
    correct_block_avx2_16<Raw>(pr, first, count);
  }
};

}  // namespace

// flatten: inline everything, the intrinsics functions included, which the always_inline chain of
// the shared templates cannot (a default-target function may not inline an AVX2 one).
SPHEREJAX_AVX2_TARGET __attribute__((flatten)) void correct_range_avx2(const Problem& pr, int64_t first, int64_t last) {
  correct_blocks<Avx2Block>(pr, first, last);
  _mm_sfence();  // the non-temporal stores are visible before the chunk is counted as finished
}

}  // namespace spherejax_fused

#endif  // SPHEREJAX_X86
