// The XLA FFI handler of the kernel: the custom call "spherejax_fused_correct" that
// spherejax._engine.fused registers with XLA's CPU backend and calls from jitted code. Its chunks
// run on XLA's intra-op thread pool (call.h).

#include <algorithm>
#include <cstdint>
#include <memory>
#include <new>

#include "call.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace spherejax_fused {
namespace {

ffi::Error Correct(ffi::ThreadPool pool, ffi::AnyBuffer raw, ffi::Buffer<ffi::F32> dark,
                   ffi::Buffer<ffi::F32> white, ffi::Buffer<ffi::F32> p,
                   ffi::Buffer<ffi::F32> coeffs, ffi::Buffer<ffi::F32> projection,
                   ffi::Buffer<ffi::F32> bias, ffi::Buffer<ffi::F32> white_xyz, ffi::Buffer<ffi::F32> whitening,
                   ffi::Buffer<ffi::F32> inducing, ffi::Buffer<ffi::F32> factor, ffi::Buffer<ffi::F32> basis,
                   float saturation, int32_t variant,
                   ffi::ResultBuffer<ffi::F32> reflectance, ffi::ResultBuffer<ffi::F32> lab,
                   ffi::ResultBuffer<ffi::U8> quality) {
  const auto dims = raw.dimensions();
  if (dims.size() != 3) return ffi::Error::InvalidArgument("raw: expected (N, P, B)");
  const int64_t images = dims[0], pixels = dims[1], bands = dims[2];
  const bool u16 = raw.element_type() == ffi::U16;
  if (!u16 && raw.element_type() != ffi::F32) {
    return ffi::Error::InvalidArgument("raw: expected uint16 or float32");
  }
  if (bands < 1 || bands > kMaxBands) return ffi::Error::InvalidArgument("bands: expected 1..64");
  if (dark.element_count() != size_t(pixels * bands) || white.element_count() != dark.element_count() ||
      p.element_count() != size_t(images * bands) || coeffs.element_count() != size_t(bands * 4) ||
      projection.element_count() != size_t(bands * kOutputs) || bias.element_count() != size_t(kOutputs) ||
      white_xyz.element_count() != 3) {
    return ffi::Error::InvalidArgument("inputs: shapes do not match raw (N, P, B)");
  }
  // The kernel residual: whitening (D, B + 1), inducing (M, B + 1), factor (M, r), basis (r, 34), r = kResidualRank.
  Residual residual;
  const auto whitening_dims = whitening.dimensions(), inducing_dims = inducing.dimensions();
  if (whitening_dims.size() != 2 || inducing_dims.size() != 2 || whitening_dims[1] != bands + 1 ||
      inducing_dims[1] != bands + 1 || factor.element_count() != size_t(inducing_dims[0] * kResidualRank) ||
      basis.element_count() != size_t(kResidualRank * kOutputs)) {
    return ffi::Error::InvalidArgument("residual: shapes do not match raw (N, P, B)");
  }
  residual.whitened_rows = whitening_dims[0];
  residual.inducing_rows = inducing_dims[0];
  residual.whitening = whitening.typed_data();
  residual.inducing = inducing.typed_data();
  residual.factor = factor.typed_data();
  residual.basis = basis.typed_data();
  if (const char* wrong = check_residual(residual)) return ffi::Error::InvalidArgument(wrong);
  const char* refused = nullptr;
  const Variant resolved = resolve_variant(variant, &refused);
  if (refused != nullptr) return ffi::Error::InvalidArgument(refused);
  std::unique_ptr<Prepared> prepared;
  try {
    prepared = prepare(raw.untyped_data(), u16, dark.typed_data(), white.typed_data(), p.typed_data(),
                       coeffs.typed_data(), projection.typed_data(), bias.typed_data(), white_xyz.typed_data(),
                       images, pixels, bands, saturation, resolved, residual, reflectance->typed_data(),
                       lab->typed_data(), quality->typed_data());
  } catch (const std::bad_alloc&) {
    return ffi::Error(ffi::ErrorCode::kResourceExhausted, "out of memory");
  }
  std::shared_ptr<Shared> shared = prepared->shared;
  run(*shared, [&] {
    const int64_t helpers = std::min<int64_t>(pool.num_threads(), shared->chunks - 1);
    for (int64_t t = 0; t < helpers; ++t) pool.Schedule([shared] { shared->work(); });
  });
  return ffi::Error::Success();
}

}  // namespace
}  // namespace spherejax_fused

// `variant`: a code of spherejax_fused::Variant (fused_correct.h); 0 lets the kernel take the
// widest the CPU runs. spherejax._engine.fused passes the one it measured fastest, the same for
// every call of a process.
XLA_FFI_DEFINE_HANDLER_SYMBOL(SpherejaxFusedCorrect, spherejax_fused::Correct,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()           // raw
                                  .Arg<ffi::Buffer<ffi::F32>>()    // dark
                                  .Arg<ffi::Buffer<ffi::F32>>()    // white
                                  .Arg<ffi::Buffer<ffi::F32>>()    // p
                                  .Arg<ffi::Buffer<ffi::F32>>()    // coeffs
                                  .Arg<ffi::Buffer<ffi::F32>>()    // projection
                                  .Arg<ffi::Buffer<ffi::F32>>()    // bias
                                  .Arg<ffi::Buffer<ffi::F32>>()    // white_xyz
                                  .Arg<ffi::Buffer<ffi::F32>>()    // residual whitening
                                  .Arg<ffi::Buffer<ffi::F32>>()    // residual inducing
                                  .Arg<ffi::Buffer<ffi::F32>>()    // residual factor
                                  .Arg<ffi::Buffer<ffi::F32>>()    // residual basis
                                  .Attr<float>("saturation")
                                  .Attr<int32_t>("variant")
                                  .Ret<ffi::Buffer<ffi::F32>>()    // reflectance
                                  .Ret<ffi::Buffer<ffi::F32>>()    // lab
                                  .Ret<ffi::Buffer<ffi::U8>>());   // quality
