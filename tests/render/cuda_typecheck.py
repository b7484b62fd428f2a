"""Type-check the CUDA kernels and lower them to NVVM IR for one compute capability, with no GPU, driver or CUDA
toolkit: Numba's typing and lowering for the CUDA target run on the CPU (a stand-in device supplies the compute
capability; PTX generation, which needs NVVM, is not done). The CUDA simulator runs kernels as plain Python and
types nothing, so this is what catches a kernel Numba could not compile for a GPU.

Run as a script with the simulator off (NUMBA_ENABLE_CUDASIM=0): prints `OK <kernel> <IR chars>` per kernel, or
`SKIP <reason>` when this Numba's internals differ (numba.cuda.compiler.compile_cuda, the dispatcher's
get_current_device); exits 1 on a typing or lowering error. Argument types are those the launches pass
(render/cuda_backend.py): C-contiguous arrays, Python ints -> int64, floats -> float64, bools -> boolean.
"""
from __future__ import annotations

import sys


def main(cc=(9, 0)) -> int:
    import numba
    from numba import types as nt

    if numba.config.ENABLE_CUDASIM:
        print("SKIP the CUDA simulator is on (NUMBA_ENABLE_CUDASIM=1)")
        return 0
    try:
        import numba.cuda.dispatcher as dispatcher
        from numba.cuda.compiler import compile_cuda
    except ImportError as exc:
        print(f"SKIP numba's CUDA target is not importable here: {exc}")
        return 0
    if not hasattr(dispatcher, "get_current_device"):
        print("SKIP this numba's CUDA dispatcher has no get_current_device to stand in for")
        return 0

    class StandIn:  # what the dispatcher asks the current device for while compiling device functions
        compute_capability = cc
        id = 0

    dispatcher.get_current_device = lambda: StandIn()
    from trisplat.render import cuda_kernels as k

    def arr(dt, nd):
        return nt.Array(dt, nd, "C")

    f32, f64, i32, i64, b = nt.float32, nt.float64, nt.int32, nt.int64, nt.boolean
    pos, faces, mat = arr(f32, 2), arr(i32, 2), arr(f64, 2)
    img3, img2 = arr(f32, 3), arr(f32, 2)
    sigs = {
        "setup_faces": (pos, faces, mat, mat, arr(f32, 2), arr(f32, 1), b, f64, f64, f64, f64, i64, i64, i64,
                        arr(f32, 2), arr(i32, 2), arr(f32, 1), arr(i32, 1), arr(i32, 1)),
        "emit_pairs": (arr(f32, 2), arr(i32, 2), arr(i32, 1), arr(i64, 1), arr(i32, 1), i64, i64, b, arr(i64, 1),
                       arr(i32, 1)),
        "raster_forward": (arr(f32, 2), arr(i32, 2), arr(i32, 1), arr(i32, 1), i64, i64, i64, i64, f64, f64, f64, f64,
                           b, arr(f32, 1), img3, img2, img2, img3, arr(i64, 2), arr(f32, 1), arr(i32, 2)),
        "raster_backward": (arr(f32, 2), arr(i32, 2), arr(i32, 1), arr(i32, 1), i64, i64, i64, i64, f64, f64, f64,
                            f64, b, img3, img2, img2, img3, img3, img2, img2, img3, arr(f32, 2)),
        "setup_backward": (pos, faces, mat, mat, arr(i32, 1), arr(i32, 1), arr(f32, 2), arr(f32, 2), arr(f32, 2),
                           arr(f32, 1)),
        "hard_setup": (pos, faces, mat, mat, f64, i64, i64, i64, arr(f32, 2), arr(i32, 2), arr(f32, 1), arr(f32, 2),
                       arr(i32, 2), arr(f32, 1), arr(i32, 1)),
        "hard_pixels": (arr(f32, 2), arr(i32, 2), arr(f32, 1), arr(i32, 1), arr(i32, 1), i64, i64, i64, i64,
                        arr(i32, 2), arr(i32, 2)),
        "hard_resolve": (arr(f32, 2), pos, faces, mat, arr(f32, 2), arr(i32, 2), b, arr(f32, 1), img3, img2, img3,
                         arr(i64, 2), arr(f32, 1)),
    }
    import inspect

    if not {"cc", "fastmath", "debug", "lineinfo"} <= set(inspect.signature(compile_cuda).parameters):
        print(f"SKIP numba.cuda.compiler.compile_cuda takes other arguments here: {inspect.signature(compile_cuda)}")
        return 0
    failed = 0
    for name, argtypes in sigs.items():
        kernel = getattr(k, name)
        try:
            cres = compile_cuda(kernel.py_func, nt.void, argtypes, debug=False, lineinfo=False,
                                fastmath=bool(kernel.targetoptions.get("fastmath")), cc=cc)
            print(f"OK {name} {len(cres.library.get_llvm_str())}")
        except Exception as exc:  # noqa: BLE001 - any typing or lowering error fails the check, with its message
            failed += 1
            print(f"FAIL {name}: {type(exc).__name__}: {exc}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
