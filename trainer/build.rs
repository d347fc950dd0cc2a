//! Makes every binary and test binary of this package find libtorch at run time without
//! `LD_LIBRARY_PATH`: an rpath to `$LIBTORCH/lib` (set by `.cargo/config.toml`). When the
//! libtorch is a CUDA build, `libtorch_cuda` is linked with `--no-as-needed`: nothing references
//! its symbols directly, so the linker would otherwise drop it and CUDA would never register.

use std::path::PathBuf;

/// Emits the rpath and CUDA link arguments for this package's binaries.
pub fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let Some(libtorch) = std::env::var_os("LIBTORCH") else {
        return;
    };
    let lib = PathBuf::from(libtorch).join("lib");
    // Resolve the `.venv/libtorch` link so the rpath survives the link being re-created.
    let lib = lib.canonicalize().unwrap_or(lib);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    if lib.join("libtorch_cuda.so").exists() {
        println!("cargo:rustc-link-search=native={}", lib.display());
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
}
