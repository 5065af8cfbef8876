// The per-pixel path of spherejax.correct as one fused CPU kernel, called from XLA (FFI).
//
// Why this exists. XLA on CPU does not fuse a matrix product with elementwise work, so the
// plain jitted path (spherejax/pipeline.py, `_correct_pixels_plain`) writes the Stage II cube
// and the white signal to memory and reads them back for the Wiener and XYZ products: about
// 500 MB a megapixel against the 297 bytes a pixel the path must move, and XLA's elementwise
// loops reach only part of the copy bandwidth (benchmarks/README.md, "Where the time of
// `correct` goes"). This kernel reads each pixel once and writes its outputs once.
//
// It computes exactly the equations of the plain path, in float32, pixel by pixel:
//   quality  bits: 1 saturated (finite raw >= saturation in some band), 2 raw not finite,
//            4 white - dark not finite and > 0 in some band, 8 the image's p not finite,
//            16 v below -kBelowDarkLimit in some band whose raw is finite and white - dark
//            finite and > 0
//   v        = (raw - dark) / (white - dark)                         (Eq. 10)
//   v_tilde  = (c1 p + c2) v + c3 p + c4                              (Eq. 17 and 23)
//   [reflectance | XYZ] = v_tilde @ projection + bias                 (the affine Wiener estimate
//            W v_tilde + r0, 16 -> 31, and the folded (B, 3) XYZ matrix with its offset r0 @
//            weights: one (B, 34) product whose accumulators start at the (34,) bias)
//   [reflectance | XYZ] += P G k(v_tilde)                              (the kernel residual A k(v) of
//            an estimator with one, E8-E10 of spherejax/estimation/kernel_residual.py: see
//            residual_of; absent when the call has no inducing points)
//   Lab      = CIE 1976 from XYZ / white_xyz                          (CIE 15:2004)
// and NaN in reflectance and Lab wherever quality != 0; a pixel whose outputs come out not finite
// (an estimate that overflows float32) gets bit 2 as well (flag_nonfinite_outputs). The tests
// compare it with the plain path on every branch (tests/test_fused.py).
//
// Each pixel goes through the same code wherever it lies (the last block of a range is padded,
// never handled by a scalar tail), so a strip of an image gives the same bits as the whole image.
//
// Layout: raw (N, P, B) uint16 or float32, dark and white (P, B), p (N, B), coeffs (B, 4),
// projection (B, 34), bias (34,), white_xyz (3,), and the residual's whitening (D, B + 1), inducing
// (M, B + 1), factor (M, 8) and basis (8, 34) (D and M multiples of 8, M = 0 for none; see
// residual_of); outputs reflectance (N, P, 31), Lab (N, P, 3), quality
// (N, P) uint8. The work is split into chunks of pixels run on XLA's intra-op thread pool.
//
// The sources, by job (setup.py compiles them into one extension, spherejax._engine._fused_correct):
//   fused_correct.h  this header: the types, the Problem of one call, the generic per-pixel code,
//                    the kernel residual's template over a lane policy (residual_of) and the
//                    block templates every instruction-set variant shares;
//   generic.cc       the generic variant: the code below compiled for three x86-64 levels
//                    (target_clones), what every band count but 16 runs;
//   avx512.cc        16 bands with AVX-512 intrinsics (its Stage II and lane policy);
//   avx2.cc          16 bands with AVX2 + FMA intrinsics (its own block shape and sum order, and
//                    its lane policy for the residual);
//   call.h, call.cc  a call: which variants the CPU runs, the variant a call asked for, the
//                    per-image constants, and the chunks shared out to threads;
//   ffi_handler.cc   the XLA FFI handler (the custom call of spherejax._engine.fused);
//   band_taps.h, registered_rows.cc
//                    the bands resampled into the reference band's geometry: what a call with
//                    band maps runs before this kernel, row by row (call.cc, work_registered);
//   register_bands.cc  a second handler, not this kernel: the same registration as a pass of its
//                    own that writes registered frames (spherejax._engine.fused_registration);
//   module.cc        the CPython module: handler(), registration_handler(), correct_arrays(),
//                    supported_variants(), capabilities(), ffi_api_version().
// No -march anywhere: each variant carries its instruction set as function attributes, and
// which one runs is chosen per call (call.cc), so one build runs on any x86-64.

#ifndef SPHEREJAX_FUSED_CORRECT_H_
#define SPHEREJAX_FUSED_CORRECT_H_

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace spherejax_fused {

constexpr int64_t kReflectance = 31;            // 400..700 nm step 10
constexpr int64_t kOutputs = kReflectance + 3;  // reflectance then X, Y, Z
constexpr int64_t kLanes = 16;                  // floats in one 512-bit vector
constexpr int64_t kPadded = 48;                 // kOutputs rounded up to whole vectors
constexpr int64_t kMaxBands = 64;
constexpr int64_t kResidualRows = 8;            // whitening and inducing rows come in multiples of this
constexpr int64_t kResidualRank = 8;            // rank of the residual's weights A = P G: 8 accumulators a lane
constexpr int64_t kBlock = 32;                  // pixels whose XYZ are turned into Lab together
constexpr int64_t kChunk = 8192;                // pixels per thread-pool task
constexpr float kLabEpsilon = 216.0f / 24389.0f;
constexpr float kLabKappa = 24389.0f / 27.0f;
// pipeline.BELOW_DARK_LIMIT (its comment says why 2 %): the same number, or the bits differ.
constexpr float kBelowDarkLimit = 0.02f;

// The instruction-set variants of the kernel, by the codes the callers pass (the FFI attribute
// `variant`, correct_arrays' argument; spherejax._engine.fused names them). Only 16 bands (the
// instrument's) have code of their own per instruction set; every other band count runs the
// generic code whichever variant was asked for. kBest: the widest the CPU runs, for callers that
// leave the choice to the kernel (spherejax._engine.fused instead measures which is fastest).
enum class Variant : int32_t { kBest = 0, kAvx512 = 1, kAvx2 = 2, kGeneric = 3 };

// GCC/Clang vector extension: 16 floats. Compiled for each target of `target_clones` (generic.cc),
// it is one zmm register with AVX-512, two ymm with AVX2, four xmm otherwise.
typedef float Vec __attribute__((vector_size(kLanes * sizeof(float)), aligned(64)));

#if defined(__x86_64__) && defined(__GNUC__)
#define SPHEREJAX_X86 1
#define SPHEREJAX_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#define SPHEREJAX_AVX512_TARGET __attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,fma")))
#define SPHEREJAX_AVX2_TARGET __attribute__((target("avx2,fma")))
#else
#define SPHEREJAX_X86 0
#define SPHEREJAX_CLONES
#endif
#define SPHEREJAX_INLINE inline __attribute__((always_inline))

struct Problem {
  const void* raw;
  bool raw_is_u16;
  // The flat index (over images and pixels) of raw's first pixel: 0, but for a call with band maps
  // (call.h, Shared::work_registered), whose raw is one registered row at a time.
  int64_t raw_first;
  const float* dark;
  const float* white;
  // Floats from one pixel's dark and white to the next: the band count, but 0 for a call with band
  // maps, whose registered rows are v' itself (dark 0 and white 1 for every pixel).
  int64_t calibration_stride;
  int64_t images, pixels, bands;
  float saturation;  // NaN: no saturation check
  Variant variant;   // which code runs (call.cc resolves kBest; never kBest here)
  // Per image and band: a = c1 p + c2 and c = c3 p + c4, so v_tilde = a v + c.
  const float* gain;
  const float* offset;
  const uint8_t* image_bad;  // per image: QUALITY 8 when some p is not finite
  const Vec* projection;     // (bands, 3) vectors: the (B, 34) matrix padded to 48 columns
  const Vec* bias;           // 3 vectors: the (34,) bias [r0 | r0 @ weights] padded to 48
  float inverse_white[3];
  // The kernel residual (residual_of), absent when inducing_rows is 0: whitening (whitened_rows,
  // B + 1), inducing (inducing_rows, B + 1), factor (inducing_rows, kResidualRank) floats, row-major;
  // basis kResidualRank x 3 Vecs (rows padded to 48 like the projection's). whitened_rows and
  // inducing_rows multiples of kResidualRows. The whitening and inducing rows are the caller's
  // scaled by sqrt(log2 e) and log2 e (call.cc, prepare): the sums come out as exponents of 2,
  // which saves the exponential one multiplication a point. residual_rank: the factor's leading
  // columns in use, kResidualRank or kResidualRank / 2 (the rest zero), so that a residual of
  // rank 4 or less takes half the multiply-adds of g.
  int64_t whitened_rows, inducing_rows, residual_rank;
  const float* whitening;
  const float* inducing;
  const float* factor;
  const Vec* basis;
  float* reflectance;
  float* lab;
  uint8_t* quality;
};

// The pixels [first, last) (flat over images and pixels) of `pr`, by each variant: the entry
// points of generic.cc, avx512.cc and avx2.cc. The last two take 16 bands only and run only on
// CPUs that have their instructions (call.cc checks both).
void correct_range_generic(const Problem& pr, int64_t first, int64_t last);
#if SPHEREJAX_X86
void correct_range_avx512(const Problem& pr, int64_t first, int64_t last);
void correct_range_avx2(const Problem& pr, int64_t first, int64_t last);
#endif

// x^(1/3) for x > 0: an exponent-dividing first guess (within 4 %), then two Halley steps
// y <- y (y^3 + 2x) / (2 y^3 + x), each cubing the relative error: within 3 ulp in float32
// (tests/test_fused.py).
// Written out because libm's cbrtf does not vectorise.
// Above 2^72 the Halley step's y (y^3 + 2x) would overflow float32 (from about 4e28), making a
// finite XYZ an infinite Lab: such x are taken times 2^-72 and their root times 2^24, both exact,
// so every x below keeps its bits and every finite x has a finite root, as jnp.cbrt's
// (equations.flag_nonfinite_outputs counts on Lab being finite where XYZ is).
SPHEREJAX_INLINE float cube_root_positive(float x) {
  const bool huge = x > 0x1p72f;
  x = huge ? x * 0x1p-72f : x;
  uint32_t bits;
  std::memcpy(&bits, &x, sizeof bits);
  bits = bits / 3u + 0x2a5137a0u;
  float y;
  std::memcpy(&y, &bits, sizeof y);
  for (int step = 0; step < 2; ++step) {
    const float y3 = y * y * y;
    y = y * (y3 + 2.0f * x) / (2.0f * y3 + x);
  }
  return huge ? y * 0x1p24f : y;
}

SPHEREJAX_INLINE float lab_f(float t) {
  const bool above = t > kLabEpsilon;
  const float root = cube_root_positive(above ? t : 1.0f);
  return above ? root : (kLabKappa / 116.0f) * t + 16.0f / 116.0f;
}

typedef int32_t IntVec __attribute__((vector_size(kLanes * sizeof(int32_t)), aligned(64)));

SPHEREJAX_INLINE Vec abs_lanes(Vec x) {
  IntVec bits;
  std::memcpy(&bits, &x, sizeof bits);
  bits &= 0x7fffffff;
  std::memcpy(&x, &bits, sizeof x);
  return x;
}

// min(max(t, -125), 0) lane by lane, as min(a, b) = (a + b - |a - b|) / 2: GCC turns vector-
// extension comparisons into scalar code (avx512.cc), and this needs none. The jax.numpy path
// clips the exponent at 0 as well (round-off can make -|u - z|^2 / 2 positive); -125 (base 2,
// e^-86.6) keeps 2^t normal (exp2_nonpositive), where jax's e^-87 = 1.6e-38 is as good as
// nothing. NaN stays NaN.
SPHEREJAX_INLINE Vec clip_exponent2(Vec t) {
  const Vec below_zero = 0.5f * (t - abs_lanes(t));
  return 0.5f * ((below_zero - 125.0f) + abs_lanes(below_zero + 125.0f));
}

// 2^t for t in [-125, 0], lane by lane (e^x with x log2(e) = t folded into the constants, call.cc):
// t = n + f with n an integer (rounded to nearest by the 1.5 x 2^23 trick) and |f| <= 1/2, 2^f by
// its Taylor polynomial of degree 6 (relative error below 1.3e-7: (ln 2 / 2)^7 / 7!), and 2^n put
// into the exponent bits (n >= -125: a normal float). Written out because libm's exp2f does not
// vectorise (tests/test_fused_residual.py compares the kernel with jax's exp).
SPHEREJAX_INLINE Vec exp2_nonpositive(Vec t) {
  const Vec magic = Vec{} + 12582912.0f;
  const Vec n = (t + magic) - magic;
  const Vec f = t - n;
  Vec p = Vec{} + 1.5403530393381609e-4f;
  p = p * f + 1.3333558146428443e-3f;
  p = p * f + 9.6181291076284772e-3f;
  p = p * f + 5.5504108664821580e-2f;
  p = p * f + 2.4022650695910071e-1f;
  p = p * f + 6.9314718055994531e-1f;
  p = p * f + 1.0f;
  const IntVec bits = (__builtin_convertvector(n, IntVec) + 127) << 23;
  Vec scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return p * scale;
}

// A lane policy: how the kernel residual (residual_of) spreads a block's pixels over the vector
// lanes of one instruction set. residual_of writes the equations once; each variant brings one
// (GenericLanes below, Avx512Lanes in avx512.cc, Avx2Lanes in avx2.cc) with
//   V                   the vector: kWidth floats, one pixel a lane, with +, * and += lane by lane
//                       and with a float (V{} is zero);
//   kWidth              floats in a V (divides kBlock);
//   kWhiteningStep, kInducingStep, kRankStep, kOutputStep
//                       whitening rows, inducing points, ranks of g and outputs whose sums are
//                       held in registers at once (the first two divide kResidualRows, the third
//                       kResidualRank);
//   static V load(const float* from), static void store(float* to, V x)
//                       kWidth floats from and to memory on a kWidth * 4-byte boundary;
//   static void exp2(V* k, int64_t n)
//                       k[j] = 2^min(k[j], 0) lane by lane for j < n, NaN kept (the kernel
//                       values k(v) from their exponents in base 2, a chunk at a time);
//   static void columns(const float (*rows)[kMaxBands], int64_t B, float (*columns)[kBlock])
//                       a block's v_tilde, rows[pixel][band], as columns[band][pixel];
//   static void write_rows(const float (*out)[kBlock], int64_t count, float* to)
//                       a block's reflectance, out[o][pixel], as a row of 31 floats per pixel
//                       at to + pixel * 31 (count pixels).
// The steps are sized to the register file: the accumulators of a step, the v_tilde vector and a
// broadcast matrix element must fit in it, or the compiler spills accumulators to the stack
// around every multiply-add. Every lane sees the same operations in the same order whatever the
// steps, so they change a policy's speed, never its results.

// acc[q] += sum_b tilde[b][first + lane] m[q * q_stride + b * b_stride] for q < N and the kWidth
// pixels from `first`, one a lane: N rows (or columns) of a matrix against the pixels' v_tilde,
// each band's vector loaded once for the N multiply-adds held in registers (residual_of).
template <int N, typename Lanes, typename V = typename Lanes::V>
SPHEREJAX_INLINE void add_band_products(const float (*tilde)[kBlock], int64_t first, int64_t B, const float* m,
                                        int64_t q_stride, int64_t b_stride, V* acc) {
  for (int64_t b = 0; b < B; ++b) {
    const V t = Lanes::load(tilde[b] + first);
#pragma GCC unroll 8
    for (int q = 0; q < N; ++q) acc[q] += t * m[q * q_stride + b * b_stride];
  }
}

// N outputs o0 .. o0 + N - 1 of [reflectance | XYZ] for kWidth pixels, one a lane (residual_of):
// bias + v_tilde . projection (the affine estimate, as correct_block computes it pixel by pixel)
// + g . basis (the kernel residual P G k(v)), into out[o][first + lane].
template <int N, int Rank, typename Lanes, typename V = typename Lanes::V>
SPHEREJAX_INLINE void outputs_of(const Problem& pr, int64_t B, const float (*tilde)[kBlock], int64_t first,
                                 const V* g, int64_t o0, float (*out)[kBlock]) {
  const float* basis = reinterpret_cast<const float*>(pr.basis) + o0;
  const float* bias = reinterpret_cast<const float*>(pr.bias) + o0;
  V acc[N];
#pragma GCC unroll 8
  for (int q = 0; q < N; ++q) acc[q] = V{} + bias[q];
  add_band_products<N, Lanes>(tilde, first, B, reinterpret_cast<const float*>(pr.projection) + o0, 1, kPadded, acc);
#pragma GCC unroll 8
  for (int64_t r = 0; r < Rank; ++r) {
#pragma GCC unroll 8
    for (int q = 0; q < N; ++q) acc[q] += g[r] * basis[r * kPadded + q];
  }
#pragma GCC unroll 8
  for (int q = 0; q < N; ++q) Lanes::store(out[o0 + q] + first, acc[q]);
}

// Inducing points taken a chunk at a time by residual_of: their kernel values wait in a stack
// buffer of this many vectors between its three passes.
constexpr int64_t kInducingChunk = 32;

// The outputs [reflectance | XYZ] of Lanes::kWidth pixels with the kernel residual (E8-E10 of
// spherejax/estimation/kernel_residual.py), one pixel a lane: their v_tilde are
// tilde[b][first + lane] (b < B), their outputs go to out[o][first + lane] (o < 34). With rows of
// the Problem's arrays
//   whitening (D, B + 1): row i = [S_i | -(S mu)_i]   so  u_i = S_i v - (S mu)_i
//   inducing (M, B + 1):  row j = [Y_j | c_j]          Y = S^T z^T, c_j = -mu . Y_j - |z_j|^2 / 2
//   factor (M, 8):        row j = G^T_j                A = P G at rank kResidualRank or less
//   basis (8, 48):        row r = [P_r | weights^T P_r]
// it computes -|u - z_j|^2 / 2 = Y_j . v + c_j - |u|^2 / 2, k_j = exp of it (clipped at 0 as the
// jax.numpy path clips), g = sum_j k_j G^T_j and the outputs bias + v . projection + g . basis.
// Padding rows are zero (a padding inducing point has factor 0). The Problem's rows carry log2 e
// (Problem: whitening, inducing), so the sums are the exponents in base 2 and k_j = 2^sum. Rank:
// the columns of G in use (Problem::residual_rank, 4 or 8): the multiply-adds of g are Rank a
// point, and the outputs' Rank more a pixel.
//
// What a point costs a pixel: B multiply-adds for its sum, 5 for its exponential's polynomial
// (AVX2, AVX-512; a sixth, the multiplication by log2 e, is folded into the constants) and Rank
// for g. The multiply-adds are the whole time of the loop: on a Zen 4 core, 0.56-0.62 ns a pixel
// a point at rank 8 (single thread, 16 bands, before log2 e was folded in), against 0.54 ns for
// those multiply-adds alone at the 7.0 G ymm multiply-adds a second measured on that core; so no
// exact kernel applies more points in the time, and the count of inducing points a calibration
// may take follows from it (spherejax/estimation/kernel_residual.py, SPEED_BOUND_POINTS).
//
// Why lanes over pixels: one pixel's work is a chain of dependent sums (|u|^2 before every
// k_j, every k_j before g), which one pixel at a time left the FMA units waiting (measured:
// 560 cycles a pixel against 240 this way); kWidth pixels a vector give every step kWidth
// independent lanes, each value loaded feeds several multiply-adds held in registers, and the
// 34 outputs take 34 x (B + 8) / kWidth multiply-adds a pixel.
//
// Why three passes over a chunk of inducing points (their sums, their exponentials, their
// products with G) rather than one: the exponential of a sum is a chain of about 15 operations
// and g's accumulators stay live across the whole loop; in one pass, a step's sums, the
// exponentials in flight and g outgrow AVX2's 16 registers. Apart, each pass holds only its own
// accumulators, and the exponentials of a chunk are independent of each other.
template <typename Lanes, int Rank>
SPHEREJAX_INLINE void residual_of(const Problem& pr, int64_t B, const float (*tilde)[kBlock], int64_t first,
                                  float (*out)[kBlock]) {
  using V = typename Lanes::V;
  constexpr int kWhitening = Lanes::kWhiteningStep, kInducing = Lanes::kInducingStep;
  constexpr int kRank = Lanes::kRankStep < Rank ? Lanes::kRankStep : Rank, kOut = Lanes::kOutputStep;
  static_assert(kResidualRows % kWhitening == 0 && kResidualRows % kInducing == 0 && Rank % kRank == 0 &&
                    Rank <= kResidualRank && kInducingChunk % kResidualRows == 0,
                "steps that divide the rows and the rank");
  const int64_t D = pr.whitened_rows, M = pr.inducing_rows, width = B + 1;
  V squared = {};
  for (int64_t i = 0; i < D; i += kWhitening) {
    const float* row = pr.whitening + i * width;
    V u[kWhitening];
#pragma GCC unroll 8
    for (int q = 0; q < kWhitening; ++q) u[q] = V{} + row[q * width + B];
    add_band_products<kWhitening, Lanes>(tilde, first, B, row, width, 1, u);
#pragma GCC unroll 8
    for (int q = 0; q < kWhitening; ++q) squared += u[q] * u[q];
  }
  const V half = 0.5f * squared;
  V g[Rank] = {};
  for (int64_t j0 = 0; j0 < M; j0 += kInducingChunk) {
    const int64_t n = std::min(kInducingChunk, M - j0);  // a multiple of kResidualRows
    V k[kInducingChunk];
    for (int64_t j = 0; j < n; j += kInducing) {
      const float* y = pr.inducing + (j0 + j) * width;
      V s[kInducing];
#pragma GCC unroll 8
      for (int q = 0; q < kInducing; ++q) s[q] = y[q * width + B] - half;
      add_band_products<kInducing, Lanes>(tilde, first, B, y, width, 1, s);
#pragma GCC unroll 8
      for (int q = 0; q < kInducing; ++q) k[j + q] = s[q];
    }
    Lanes::exp2(k, n);
    for (int r0 = 0; r0 < Rank; r0 += kRank) {
      V acc[kRank];
#pragma GCC unroll 8
      for (int r = 0; r < kRank; ++r) acc[r] = g[r0 + r];
      for (int64_t j = 0; j < n; ++j) {
        const float* f = pr.factor + (j0 + j) * kResidualRank + r0;
#pragma GCC unroll 8
        for (int r = 0; r < kRank; ++r) acc[r] += k[j] * f[r];
      }
#pragma GCC unroll 8
      for (int r = 0; r < kRank; ++r) g[r0 + r] = acc[r];
    }
  }
  for (int64_t o0 = 0; o0 + kOut <= kOutputs; o0 += kOut) outputs_of<kOut, Rank, Lanes>(pr, B, tilde, first, g, o0, out);
  if constexpr (kOutputs % kOut != 0) {
    outputs_of<kOutputs % kOut, Rank, Lanes>(pr, B, tilde, first, g, kOutputs - kOutputs % kOut, out);
  }
}

// residual_of for every pixel of a block, kWidth at a time, at the call's rank (Problem).
template <typename Lanes>
SPHEREJAX_INLINE void residual_of_block(const Problem& pr, int64_t B, const float (*tilde)[kBlock],
                                        float (*out)[kBlock]) {
  if (pr.residual_rank <= kResidualRank / 2) {
    for (int64_t lane0 = 0; lane0 < kBlock; lane0 += Lanes::kWidth) {
      residual_of<Lanes, kResidualRank / 2>(pr, B, tilde, lane0, out);
    }
  } else {
    for (int64_t lane0 = 0; lane0 < kBlock; lane0 += Lanes::kWidth) {
      residual_of<Lanes, kResidualRank>(pr, B, tilde, lane0, out);
    }
  }
}

// The lane policy (see above) of the generic variant and the AVX-512 one's base: 16 floats a
// vector, one zmm register with AVX-512 (32 of them: 8 sums a step fit beside g), written in
// plain C++ for any band count.
struct GenericLanes {
  using V = Vec;
  static constexpr int kWidth = kLanes;
  static constexpr int kWhiteningStep = 8, kInducingStep = 8, kRankStep = 8, kOutputStep = 8;

  static SPHEREJAX_INLINE Vec load(const float* from) {
    Vec x;
    std::memcpy(&x, from, sizeof x);
    return x;
  }
  static SPHEREJAX_INLINE void store(float* to, Vec x) { std::memcpy(to, &x, sizeof x); }

  static SPHEREJAX_INLINE void exp2(Vec* k, int64_t n) {
    for (int64_t j = 0; j < n; ++j) k[j] = exp2_nonpositive(clip_exponent2(k[j]));
  }

  static SPHEREJAX_INLINE void write_rows(const float (*out)[kBlock], int64_t count, float* to) {
    for (int64_t i = 0; i < count; ++i) {
      for (int64_t o = 0; o < kReflectance; ++o) to[i * kReflectance + o] = out[o][i];
    }
  }

  static SPHEREJAX_INLINE void columns(const float (*rows)[kMaxBands], int64_t B, float (*columns)[kBlock]) {
    for (int64_t i = 0; i < kBlock; ++i) {
      for (int64_t b = 0; b < B; ++b) columns[b][i] = rows[i][b];
    }
  }
};

// Quality bits and v_tilde (Eq. 10, 17, 23) of one pixel, any band count: the generic Stage II.
// A Stage II is a type with kBands (its band count, 0: any, pr.bands) and
//   template <typename Raw> static uint8_t run(const Problem& pr, const Raw* r, const float* d,
//                                              const float* w, const float* a, const float* c,
//                                              float* tilde)
// which reads one pixel's raw r, dark d, white w (B each) and its image's gain a and offset c (B
// each), writes its v_tilde (B) and returns its quality bits but 8. avx512.cc and avx2.cc have one
// each for 16 bands.
struct GenericStage2 {
  static constexpr int64_t kBands = 0;

  template <typename Raw>
  static SPHEREJAX_INLINE uint8_t run(const Problem& pr, const Raw* r, const float* d, const float* w,
                                      const float* a, const float* c, float* tilde) {
    int32_t bits = 0;
    for (int64_t b = 0; b < pr.bands; ++b) {
      const float value = static_cast<float>(r[b]);
      const float signal = w[b] - d[b];
      const bool value_finite = std::isfinite(value);
      const bool flat_field_ok = (signal > 0.0f) & std::isfinite(signal);
      const float v = (value - d[b]) / signal;
      bits |= (value_finite & (value >= pr.saturation)) | (!value_finite << 1) | (!flat_field_ok << 2) |
              ((value_finite & flat_field_ok & (v < -kBelowDarkLimit)) << 4);
      tilde[b] = a[b] * v + c[b];
    }
    return static_cast<uint8_t>(bits);
  }
};

// The (image, pixel) of each of the kBlock pixels of a block that starts at `first` (flat over
// images and pixels): later ones step on without a division. The padding pixels of a last block
// (i >= count) repeat the block's first pixel: the same code runs for them, and nothing of theirs
// is written.
struct BlockPixels {
  int64_t image, pixel;
  const int64_t first_image, first_pixel, count;

  SPHEREJAX_INLINE BlockPixels(const Problem& pr, int64_t first, int64_t count)
      : image(first / pr.pixels), pixel(first - image * pr.pixels), first_image(image), first_pixel(pixel),
        count(count) {}
  // Call at the start of pixel i of the block, before its pixel is read.
  SPHEREJAX_INLINE void at(int64_t i) {
    if (i == count) image = first_image, pixel = first_pixel;
  }
  SPHEREJAX_INLINE int64_t flat(const Problem& pr) const { return image * pr.pixels + pixel; }
  // Call at the end of pixel i of the block.
  SPHEREJAX_INLINE void next(const Problem& pr, int64_t i) {
    if (i < count && ++pixel == pr.pixels) pixel = 0, ++image;
  }
};

// Stage II (a Stage II type above) of the pixel `at` points to, into tilde (B floats): its
// quality bits, the image's 8 included. A bad pixel's v_tilde becomes NaN, which NaN x anything
// carries into every output.
template <typename Raw, typename Stage2>
SPHEREJAX_INLINE uint8_t stage2_at(const Problem& pr, const BlockPixels& at, float* tilde) {
  const int64_t B = Stage2::kBands ? Stage2::kBands : pr.bands;
  const Raw* raw = static_cast<const Raw*>(pr.raw) + (at.flat(pr) - pr.raw_first) * B;
  const int64_t calibration = at.pixel * pr.calibration_stride;
  uint8_t q = Stage2::template run<Raw>(pr, raw, pr.dark + calibration, pr.white + calibration,
                                        pr.gain + at.image * B, pr.offset + at.image * B, tilde);
  q |= pr.image_bad[at.image] * 8;
  if (q) std::fill(tilde, tilde + B, NAN);
  return q;
}

// Stage II (stage2_at) of the kBlock pixels of a block that starts at `first`, count of them real
// (BlockPixels), pixel i's v_tilde into rows[i] and its quality bits into quality[i]: the first pass
// of every block that runs Stage II for a whole block before its projections.
template <typename Raw, typename Stage2, int64_t kStride>
SPHEREJAX_INLINE void stage2_of_block(const Problem& pr, int64_t first, int64_t count, float (*rows)[kStride],
                                      uint8_t* quality) {
  BlockPixels at(pr, first, count);
  for (int64_t i = 0; i < kBlock; ++i) {
    at.at(i);
    quality[i] = stage2_at<Raw, Stage2>(pr, at, rows[i]);
    at.next(pr, i);
  }
}

// Outputs that are not finite on a pixel the flags call good: a finite v_tilde whose estimate
// overflows float32 (raw of 1e38 over a white signal of one count, a calibration's weights of
// 3e38 made without its checks). Such a pixel gets Quality.NONFINITE (2) and NaN in its
// reflectance and Lab, as spherejax.equations.flag_nonfinite_outputs defines it, so that every
// output is NaN exactly where quality says so.
//
// How it costs next to nothing: a sum of outputs is not finite when one of them is not (or when
// finite ones overflow, which only sends the block here for nothing). Each block sums its outputs
// (correct_block: its good pixels' three vectors, still in registers, three additions a pixel;
// residual_block_suspect; the AVX2 block's finish, over all its pixels); only a block whose sum is
// not finite (none, in an ordinary image; one with a bad pixel, whose outputs are NaN, for the AVX2
// one) goes through its good pixels one by one here, exactly: x * 0 is +-0 for a finite x and NaN
// for an infinite or NaN one, so their sum is 0 exactly when every term is finite.
//
// rows: the block's reflectance, a row of 31 floats per pixel; lab: pixel i's channel c at
// lab[i * pixel_stride + c * channel_stride]; quality: the block's bits, updated.
SPHEREJAX_INLINE void flag_nonfinite_outputs(int64_t count, float* rows, float* lab, int64_t pixel_stride,
                                             int64_t channel_stride, uint8_t* quality) {
  for (int64_t i = 0; i < count; ++i) {
    if (quality[i]) continue;  // already NaN in every output, with its own bits
    float probe = 0.0f;
    for (int64_t o = 0; o < kReflectance; ++o) probe += rows[i * kReflectance + o] * 0.0f;
    for (int64_t c = 0; c < 3; ++c) probe += lab[i * pixel_stride + c * channel_stride] * 0.0f;
    if (probe == 0.0f) continue;
    quality[i] |= 2;
    std::fill(rows + i * kReflectance, rows + (i + 1) * kReflectance, NAN);
    for (int64_t c = 0; c < 3; ++c) lab[i * pixel_stride + c * channel_stride] = NAN;
  }
}

// Whether a good pixel of a residual block (outputs out[o][pixel], o < 34) may have an output that
// is not finite: per pixel, the sum of its outputs, a lane per pixel (34 vector additions for 16
// pixels), then its quality.
SPHEREJAX_INLINE bool residual_block_suspect(const float (*out)[kBlock], int64_t count, const uint8_t* quality) {
  alignas(64) float probes[kBlock];
  for (int64_t lane0 = 0; lane0 < kBlock; lane0 += kLanes) {
    Vec probe = {};
    for (int64_t o = 0; o < kOutputs; ++o) {
      Vec x;
      std::memcpy(&x, out[o] + lane0, sizeof x);
      probe += x;
    }
    std::memcpy(probes + lane0, &probe, sizeof probe);
  }
  bool suspect = false;
  for (int64_t i = 0; i < count; ++i) suspect |= (quality[i] == 0) & !(probes[i] * 0.0f == 0.0f);
  return suspect;
}

// Whether a probe (a sum of outputs, flag_nonfinite_outputs) is finite in every lane: once per block.
SPHEREJAX_INLINE bool probe_is_finite(Vec probe) {
  float lanes[kLanes];
  std::memcpy(lanes, &probe, sizeof lanes);
  float zero = 0.0f;
  for (int64_t l = 0; l < kLanes; ++l) zero += lanes[l] * 0.0f;
  return zero == 0.0f;
}

// Lab and the quality of a block's pixels from their XYZ (xyz[c][i]) and quality bits, once the
// block's reflectance rows are in the outputs. suspect: whether a good pixel of the block may have
// an output that is not finite (its caller's probe of the reflectance and XYZ, which Lab follows:
// lab_f is finite for every finite XYZ); then each good pixel is checked (flag_nonfinite_outputs).
SPHEREJAX_INLINE void finish_block(const Problem& pr, int64_t first, int64_t count, const float (*xyz)[kBlock],
                                   uint8_t* quality, bool suspect) {
  alignas(64) float lab[3][kBlock];
  for (int64_t i = 0; i < kBlock; ++i) {
    const float fx = lab_f(xyz[0][i] * pr.inverse_white[0]);
    const float fy = lab_f(xyz[1][i] * pr.inverse_white[1]);
    const float fz = lab_f(xyz[2][i] * pr.inverse_white[2]);
    lab[0][i] = 116.0f * fy - 16.0f;
    lab[1][i] = 500.0f * (fx - fy);
    lab[2][i] = 200.0f * (fy - fz);
  }
  if (suspect) flag_nonfinite_outputs(count, pr.reflectance + first * kReflectance, &lab[0][0], 1, kBlock, quality);
  for (int64_t i = 0; i < count; ++i) {
    float* out = pr.lab + (first + i) * 3;
    out[0] = lab[0][i];
    out[1] = lab[1][i];
    out[2] = lab[2][i];
    pr.quality[first + i] = quality[i];
  }
}

// One block of up to kBlock pixels starting at `first` (flat over images and pixels), one pixel
// at a time: Stage II, the projection with the vector extension's Vec, then the block's Lab. The
// generic variant's block (GenericStage2) and the AVX-512 one's (its 16-band Stage II: a Vec is one
// zmm register there, and the projection below is as fast as intrinsics would make it).
template <typename Raw, typename Stage2>
SPHEREJAX_INLINE void correct_block(const Problem& pr, int64_t first, int64_t count) {
  const int64_t B = Stage2::kBands ? Stage2::kBands : pr.bands;
  alignas(64) float xyz[3][kBlock];
  alignas(64) float tilde[kMaxBands];
  uint8_t quality[kBlock];
  Vec probe = {};
  BlockPixels at(pr, first, count);
  for (int64_t i = 0; i < kBlock; ++i) {
    at.at(i);
    const int64_t flat = at.flat(pr);
    quality[i] = stage2_at<Raw, Stage2>(pr, at, tilde);
    // Separate accumulators for even and odd bands halve the chain of dependent FMAs; named
    // variables, not an array, so that they stay in registers. The even ones start at the bias
    // (the estimator's offset): no extra operation per pixel, and a zero bias gives the bits of
    // a zero start. A bad pixel's NaN still reaches every output (NaN + bias is NaN).
    Vec even0 = pr.bias[0], even1 = pr.bias[1], even2 = pr.bias[2], odd0 = {}, odd1 = {}, odd2 = {};
    int64_t b = 0;
#pragma GCC unroll 8
    for (; b + 1 < B; b += 2) {
      const Vec* m = pr.projection + 3 * b;
      const float s = tilde[b], t = tilde[b + 1];
      even0 += s * m[0], even1 += s * m[1], even2 += s * m[2];
      odd0 += t * m[3], odd1 += t * m[4], odd2 += t * m[5];
    }
    if (b < B) {
      const Vec* m = pr.projection + 3 * b;
      even0 += tilde[b] * m[0], even1 += tilde[b] * m[1], even2 += tilde[b] * m[2];
    }
    const Vec out0 = even0 + odd0, out1 = even1 + odd1, out2 = even2 + odd2;
    // The good pixels' outputs, reflectance and XYZ (out2's padding lanes are 0 for a finite
    // v_tilde), summed for flag_nonfinite_outputs: three additions a pixel.
    if (quality[i] == 0) probe += out0 + out1 + out2;
    if (i < count) {
      float* out = pr.reflectance + flat * kReflectance;
      std::memcpy(out, &out0, sizeof(Vec));
      std::memcpy(out + kLanes, &out1, (kReflectance - kLanes) * sizeof(float));
    }
    xyz[0][i] = out1[kReflectance - kLanes];
    xyz[1][i] = out2[0];
    xyz[2][i] = out2[1];
    at.next(pr, i);
  }
  finish_block(pr, first, count, xyz, quality, !probe_is_finite(probe));
}

// correct_block for a call with a kernel residual: Stage II pixel by pixel, then the outputs
// Lanes::kWidth pixels at a time (residual_of: the affine estimate and the residual, band by band
// and output by output), the reflectance turned back into a row per pixel (Lanes::write_rows),
// then Lab. The block's pixels are consecutive in the outputs (flat index first + i).
template <typename Raw, typename Stage2, typename Lanes>
SPHEREJAX_INLINE void correct_block_with_residual(const Problem& pr, int64_t first, int64_t count) {
  const int64_t B = Stage2::kBands ? Stage2::kBands : pr.bands;
  alignas(64) float rows[kBlock][kMaxBands];
  alignas(64) float tilde[kMaxBands][kBlock];
  alignas(64) float out[kPadded][kBlock];
  uint8_t quality[kBlock];
  stage2_of_block<Raw, Stage2>(pr, first, count, rows, quality);
  Lanes::columns(rows, B, tilde);
  residual_of_block<Lanes>(pr, B, tilde, out);
  Lanes::write_rows(out, count, pr.reflectance + first * kReflectance);
  finish_block(pr, first, count, out + kReflectance, quality, residual_block_suspect(out, count, quality));
}

// correct_block with the Stage II `Stage2`, as a Block type for correct_blocks; the residual's
// block, with the lane policy `Lanes`, where the call has one.
template <typename Stage2, typename Lanes>
struct PixelByPixel {
  template <typename Raw>
  static SPHEREJAX_INLINE void run(const Problem& pr, int64_t first, int64_t count) {
    if (pr.inducing_rows > 0) {
      correct_block_with_residual<Raw, Stage2, Lanes>(pr, first, count);
    } else {
      correct_block<Raw, Stage2>(pr, first, count);
    }
  }
};

// The pixels [first, last) block by block, by `Block::run<Raw>(pr, first, count)` (Raw: the raw
// dtype of pr), the last block partial: the body of every variant's entry point.
template <typename Block, typename Raw>
SPHEREJAX_INLINE void correct_blocks_of(const Problem& pr, int64_t first, int64_t last) {
  for (int64_t block = first; block < last; block += kBlock) {
    Block::template run<Raw>(pr, block, std::min(kBlock, last - block));
  }
}

template <typename Block>
SPHEREJAX_INLINE void correct_blocks(const Problem& pr, int64_t first, int64_t last) {
  if (pr.raw_is_u16) {
    correct_blocks_of<Block, uint16_t>(pr, first, last);
  } else {
    correct_blocks_of<Block, float>(pr, first, last);
  }
}

}  // namespace spherejax_fused

#endif  // SPHEREJAX_FUSED_CORRECT_H_
