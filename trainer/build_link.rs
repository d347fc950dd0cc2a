//! How a binary of this workspace links the libtorch tch uses (`$LIBTORCH`, set by
//! `.cargo/config.toml`), shared by `trainer/build.rs` and `tests/build.rs`:
//! - an rpath to `$LIBTORCH/lib`, so no `LD_LIBRARY_PATH` is needed;
//! - when that libtorch is a CUDA build, `libtorch_cuda` with `--no-as-needed`: nothing references
//!   its symbols directly, so the linker would otherwise drop it and CUDA would never register.

use std::path::PathBuf;

/// The resolved libtorch folder and whether it is a CUDA build, after emitting the link
/// arguments for this package's binaries.
pub fn emit() -> (PathBuf, bool) {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let Some(libtorch) = std::env::var_os("LIBTORCH") else {
        panic!("LIBTORCH is not set: run scripts/setup.sh (it creates .venv/libtorch, which .cargo/config.toml names)");
    };
    let libtorch = PathBuf::from(libtorch);
    // Resolve the `.venv/libtorch` link so the rpath survives the link being re-created.
    let libtorch = libtorch.canonicalize().unwrap_or(libtorch);
    let lib = libtorch.join("lib");
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    let cuda = lib.join("libtorch_cuda.so").exists();
    if cuda {
        println!("cargo:rustc-link-search=native={}", lib.display());
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
    (libtorch, cuda)
}
