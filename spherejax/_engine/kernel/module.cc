// The CPython module spherejax._engine._fused_correct: the kernel's FFI handler as a capsule for
// jax.ffi.register_ffi_target, the kernel on buffers without XLA, what spherejax._engine.fused
// needs to choose a variant (spherejax/_engine/fused.py), and what the kernel supports
// (capabilities()).

#include <Python.h>  // first, as Python asks

#include <algorithm>
#include <cstdint>
#include <memory>
#include <new>
#include <thread>
#include <vector>

#include "call.h"
#include "xla/ffi/api/c_api.h"

using namespace spherejax_fused;

// Defined by XLA_FFI_DEFINE_HANDLER_SYMBOL in ffi_handler.cc (extern "C").
extern "C" XLA_FFI_Error* SpherejaxFusedCorrect(XLA_FFI_CallFrame* call_frame);
// Defined by XLA_FFI_DEFINE_HANDLER_SYMBOL in register_bands.cc (extern "C").
extern "C" XLA_FFI_Error* SpherejaxRegisterBands(XLA_FFI_CallFrame* call_frame);

// handler(): the XLA FFI handler of the fused correction (ffi_handler.cc) as a capsule.
static PyObject* handler(PyObject*, PyObject*) {
  return PyCapsule_New(reinterpret_cast<void*>(&SpherejaxFusedCorrect), nullptr, nullptr);
}

// registration_handler(): the XLA FFI handler of the band registration (register_bands.cc).
static PyObject* registration_handler(PyObject*, PyObject*) {
  return PyCapsule_New(reinterpret_cast<void*>(&SpherejaxRegisterBands), nullptr, nullptr);
}

// correct_arrays(raw, raw_is_u16, dark, white, p, coeffs, projection, bias, white_xyz, whitening,
// inducing, factor, basis, images, pixels, bands, whitened_rows, inducing_rows, saturation, variant,
// threads, reflectance, lab, quality): the same kernel on
// C-contiguous buffers from Python, run by the calling thread and threads - 1 helpers, without
// XLA. spherejax._engine.fused.correct_arrays checks dtypes; this checks each buffer's byte size, so
// that nothing is read or written outside a buffer, and that this CPU runs the variant (a code of
// spherejax_fused::Variant: 0 the widest it runs, or VARIANT_AVX512, VARIANT_AVX2, VARIANT_GENERIC).
// Releases the GIL while it runs.
//
// An optional last argument, registration = (inverse_signal, maps, height, width), makes it the call
// of a calibration with band maps (call.h, register_bands_first): raw and dark are then the native
// frames (pixels = height * width), inverse_signal (P, B) their 1 / (white - dark) (0 without a flat
// field), maps (B, 2, 3) float32; white is not read.
static PyObject* correct_arrays(PyObject*, PyObject* args) {
  Py_buffer in[12] = {}, out[3] = {}, taps[2] = {};
  int u16 = 0, variant = 0;
  long long images = 0, pixels = 0, bands = 0, whitened_rows = 0, inducing_rows = 0, height = 0, width = 0;
  float saturation = 0.0f;
  Py_ssize_t threads = 1;
  PyObject* registration = Py_None;
  if (!PyArg_ParseTuple(args, "y*py*y*y*y*y*y*y*y*y*y*y*LLLLLfinw*w*w*|O", &in[0], &u16, &in[1], &in[2], &in[3],
                        &in[4], &in[5], &in[6], &in[7], &in[8], &in[9], &in[10], &in[11], &images, &pixels,
                        &bands, &whitened_rows, &inducing_rows, &saturation, &variant, &threads, &out[0], &out[1],
                        &out[2], &registration)) {
    return nullptr;  // PyArg_ParseTuple releases what it had taken
  }
  const bool registered = registration != Py_None;
  if (registered && !PyArg_ParseTuple(registration, "y*y*LL", &taps[0], &taps[1], &height, &width)) {
    for (auto& buffer : in) PyBuffer_Release(&buffer);
    for (auto& buffer : out) PyBuffer_Release(&buffer);
    return nullptr;
  }
  const long long expected_in[12] = {images * pixels * bands * (u16 ? 2 : 4), pixels * bands * 4,
                                     pixels * bands * 4, images * bands * 4, bands * 4 * 4,
                                     bands * kOutputs * 4, kOutputs * 4, 3 * 4,
                                     (bands + 1) * whitened_rows * 4, (bands + 1) * inducing_rows * 4,
                                     inducing_rows * kResidualRank * 4, kResidualRank * kOutputs * 4};
  Residual residual;
  residual.whitened_rows = whitened_rows;
  residual.inducing_rows = inducing_rows;
  const long long expected_out[3] = {images * pixels * kReflectance * 4, images * pixels * 3 * 4, images * pixels};
  bool sizes_match = images >= 0 && pixels >= 0 && bands >= 1 && bands <= kMaxBands && threads >= 1;
  for (int k = 0; k < 12; ++k) sizes_match &= in[k].len == expected_in[k];
  const char* wrong_residual = check_residual(residual);
  sizes_match &= wrong_residual == nullptr;
  residual.whitening = static_cast<const float*>(in[8].buf);
  residual.inducing = static_cast<const float*>(in[9].buf);
  residual.factor = static_cast<const float*>(in[10].buf);
  residual.basis = static_cast<const float*>(in[11].buf);
  for (int k = 0; k < 3; ++k) sizes_match &= out[k].len == expected_out[k];
  if (registered) {
    sizes_match &= height >= 1 && width >= 1 && height * width == pixels && taps[0].len == pixels * bands * 4 &&
                   taps[1].len == bands * 6 * 4;
  }
  const char* refused = nullptr;
  const Variant resolved = resolve_variant(variant, &refused);
  std::unique_ptr<Prepared> prepared;
  if (sizes_match && refused == nullptr && images * pixels > 0) {
    try {
      prepared = prepare(
        in[0].buf, u16 != 0, static_cast<const float*>(in[1].buf), static_cast<const float*>(in[2].buf),
        static_cast<const float*>(in[3].buf), static_cast<const float*>(in[4].buf),
        static_cast<const float*>(in[5].buf), static_cast<const float*>(in[6].buf),
        static_cast<const float*>(in[7].buf), images, pixels, bands, saturation, resolved, residual,
        static_cast<float*>(out[0].buf), static_cast<float*>(out[1].buf), static_cast<uint8_t*>(out[2].buf));
      if (registered) {
        spherejax_bands::NativeFrames native;
        native.raw = in[0].buf;
        native.u16 = u16 != 0;
        native.height = height, native.width = width, native.bands = bands;
        native.dark = static_cast<const float*>(in[1].buf);
        native.inverse_signal = static_cast<const float*>(taps[0].buf);
        native.maps = static_cast<const float*>(taps[1].buf);
        native.saturation = saturation;
        register_bands_first(*prepared, native);
      }
    } catch (const std::bad_alloc&) {
      for (auto& buffer : in) PyBuffer_Release(&buffer);
      for (auto& buffer : out) PyBuffer_Release(&buffer);
      for (auto& buffer : taps) PyBuffer_Release(&buffer);
      return PyErr_NoMemory();
    }
    Shared& shared = *prepared->shared;
    std::vector<std::thread> helpers;
    Py_BEGIN_ALLOW_THREADS
    run(shared, [&] {
      const int64_t count = std::min<int64_t>(threads - 1, shared.chunks - 1);
      try {
        for (int64_t t = 0; t < count; ++t) helpers.emplace_back([&shared] { shared.work(); });
      } catch (...) {  // std::system_error or bad_alloc: no more threads to be had
        // The threads started and this one do all the chunks.
      }
    });
    for (auto& helper : helpers) helper.join();
    Py_END_ALLOW_THREADS
  }
  for (auto& buffer : in) PyBuffer_Release(&buffer);
  for (auto& buffer : out) PyBuffer_Release(&buffer);
  for (auto& buffer : taps) PyBuffer_Release(&buffer);
  if (!sizes_match) {
    PyErr_SetString(PyExc_ValueError, wrong_residual != nullptr ? wrong_residual
                                      : "correct_arrays: buffer sizes do not match images, pixels and bands");
    return nullptr;
  }
  if (refused != nullptr) {
    PyErr_Format(PyExc_ValueError, "correct_arrays: %s, got %d", refused, variant);
    return nullptr;
  }
  Py_RETURN_NONE;
}

// supported_variants() -> tuple of str: the variants this build has and this CPU runs, widest
// first ("avx512", "avx2", "generic"; "generic" always). spherejax._engine.fused times these and
// passes the fastest; the code of each is the module's VARIANT_<NAME> constant.
static PyObject* supported_variants(PyObject*, PyObject*) {
  const char* names[3];
  Py_ssize_t count = 0;
  for (Variant variant : {Variant::kAvx512, Variant::kAvx2, Variant::kGeneric}) {
    const int32_t code = static_cast<int32_t>(variant);
    if (variant_supported(code)) names[count++] = variant_name(code);
  }
  PyObject* tuple = PyTuple_New(count);
  for (Py_ssize_t k = 0; tuple != nullptr && k < count; ++k) {
    PyObject* name = PyUnicode_FromString(names[k]);
    if (name == nullptr) {
      Py_DECREF(tuple);
      return nullptr;
    }
    PyTuple_SET_ITEM(tuple, k, name);  // steals the reference
  }
  return tuple;
}

// capabilities() -> dict: what the kernel computes, for spherejax._engine to read rather than
// repeat (fused_correct.h says why each is what it is):
//   "max_bands"          int: the most bands a call takes (kMaxBands, 64);
//   "variant_bands"      int: the band count with code of its own per variant (16); every other
//                        band count runs the generic code whichever variant is asked for;
//   "raw_dtypes"         tuple of str: the raw dtypes taken ("uint16", "float32");
//   "residual_rank"      int: the rank of the kernel residual's weights A = P G (factor (M, r),
//                        basis (r, 34)) a call passes (kResidualRank, 8); a residual of lower rank
//                        comes padded with zeros, one of higher rank is not the kernel's;
//   "residual_rows"      int: whitening and inducing rows come in multiples of this (8), zero rows
//                        appended (a padding inducing point has factor 0);
//   "residual_variants"  tuple of str: the variants whose code applies the kernel residual
//                        ("avx512", "avx2", "generic": all of them; which of them this CPU runs is
//                        supported_variants()).
static PyObject* capabilities(PyObject*, PyObject*) {
  constexpr Variant kResidualVariants[] = {Variant::kAvx512, Variant::kAvx2, Variant::kGeneric};
  const char* names[3];
  for (int k = 0; k < 3; ++k) names[k] = variant_name(static_cast<int32_t>(kResidualVariants[k]));
  return Py_BuildValue("{s:L,s:L,s:(ss),s:L,s:L,s:(sss)}", "max_bands", static_cast<long long>(kMaxBands),
                       "variant_bands", static_cast<long long>(kLanes), "raw_dtypes", "uint16", "float32",
                       "residual_rank", static_cast<long long>(kResidualRank), "residual_rows",
                       static_cast<long long>(kResidualRows), "residual_variants", names[0], names[1], names[2]);
}

// ffi_api_version() -> (major, minor): the XLA FFI API version of the headers this was compiled
// against, which XLA compares with its own when the handler is registered (setup.py).
static PyObject* ffi_api_version(PyObject*, PyObject*) {
  return Py_BuildValue("(ii)", XLA_FFI_API_MAJOR, XLA_FFI_API_MINOR);
}

static PyMethodDef methods[] = {
    {"handler", handler, METH_NOARGS, "The XLA FFI handler of the fused correction, as a capsule."},
    {"registration_handler", registration_handler, METH_NOARGS,
     "The XLA FFI handler of the band registration, as a capsule."},
    {"ffi_api_version", ffi_api_version, METH_NOARGS, "The XLA FFI API version compiled against, (major, minor)."},
    {"correct_arrays", correct_arrays, METH_VARARGS, "The fused correction on C-contiguous buffers, without XLA."},
    {"supported_variants", supported_variants, METH_NOARGS,
     "The instruction-set variants this build has and this CPU runs, widest first."},
    {"capabilities", capabilities, METH_NOARGS,
     "capabilities() -> dict: what the kernel computes.\n\n"
     "max_bands (int): the most bands a call takes.\n"
     "variant_bands (int): the band count with code of its own per variant; every other band count runs the "
     "generic code whichever variant is asked for.\n"
     "raw_dtypes (tuple of str): the raw dtypes taken.\n"
     "residual_rank (int): the rank r of the kernel residual's weights A = P G a call passes (factor (M, r), "
     "basis (r, 34)); lower ranks come padded with zeros.\n"
     "residual_rows (int): whitening and inducing rows come in multiples of this, zero rows appended.\n"
     "residual_variants (tuple of str): the variants whose code applies the kernel residual (which of them "
     "this CPU runs: supported_variants())."},
    {nullptr, nullptr, 0, nullptr},
};

static PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fused_correct",
                             "Fused CPU kernel of spherejax.correct (see spherejax/_engine/fused.py).", -1,
                             methods};

PyMODINIT_FUNC PyInit__fused_correct() {
  PyObject* m = PyModule_Create(&module);
  if (m == nullptr) return nullptr;
  // The codes of the variants (spherejax_fused::Variant), for correct_arrays and the FFI
  // attribute `variant`: spherejax._engine.fused reads them here rather than repeating them.
  const struct {
    const char* name;
    Variant code;
  } constants[] = {{"VARIANT_BEST", Variant::kBest},
                   {"VARIANT_AVX512", Variant::kAvx512},
                   {"VARIANT_AVX2", Variant::kAvx2},
                   {"VARIANT_GENERIC", Variant::kGeneric}};
  for (const auto& constant : constants) {
    if (PyModule_AddIntConstant(m, constant.name, static_cast<long>(constant.code)) != 0) {
      Py_DECREF(m);
      return nullptr;
    }
  }
  return m;
}
