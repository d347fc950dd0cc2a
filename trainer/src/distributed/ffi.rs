//! The only `unsafe` in the trainer: calls into the c10d shim (`trainer/csrc/`, built by
//! `build.rs` against the libtorch tch links), and the one autograd setter tch lacks
//! ([`set_grad`]). Each wrapper owns its C++ object and frees it on drop; every call turns the
//! shim's returned message into an [`FfiError`].
#![allow(unsafe_code)]

use std::ffi::{CStr, CString, c_char, c_int, c_void};

use tch::Tensor;

#[repr(C)]
struct RawStore {
    _private: [u8; 0],
}
#[repr(C)]
struct RawGroup {
    _private: [u8; 0],
}
#[repr(C)]
struct RawWork {
    _private: [u8; 0],
}

unsafe extern "C" {
    fn trainer_c10d_free_string(message: *mut c_char);
    fn trainer_c10d_free_bytes(bytes: *mut u8);
    fn trainer_c10d_store_new(
        host: *const c_char,
        port: u16,
        is_server: c_int,
        world_size: i64,
        timeout_ms: i64,
        prefix: *const c_char,
        out: *mut *mut RawStore,
    ) -> *mut c_char;
    fn trainer_c10d_store_free(store: *mut RawStore);
    fn trainer_c10d_store_set(store: *mut RawStore, key: *const c_char, value: *const u8, len: usize) -> *mut c_char;
    fn trainer_c10d_store_get(
        store: *mut RawStore,
        key: *const c_char,
        timeout_ms: i64,
        value: *mut *mut u8,
        len: *mut usize,
    ) -> *mut c_char;
    fn trainer_c10d_store_check(store: *mut RawStore, key: *const c_char, present: *mut c_int) -> *mut c_char;
    fn trainer_c10d_gloo_new(
        store: *mut RawStore,
        rank: c_int,
        size: c_int,
        timeout_ms: i64,
        out: *mut *mut RawGroup,
    ) -> *mut c_char;
    fn trainer_c10d_nccl_new(
        store: *mut RawStore,
        rank: c_int,
        size: c_int,
        timeout_ms: i64,
        out: *mut *mut RawGroup,
    ) -> *mut c_char;
    fn trainer_c10d_has_nccl() -> c_int;
    fn trainer_c10d_cuda_mem_get_info(device: c_int, free_bytes: *mut u64, total_bytes: *mut u64) -> c_int;
    fn trainer_c10d_cuda_memory_peaks(device: c_int, allocated: *mut u64, reserved: *mut u64, reset: c_int) -> c_int;
    fn trainer_c10d_group_free(group: *mut RawGroup);
    fn trainer_c10d_allreduce_sum(
        group: *mut RawGroup,
        tensor: *mut c_void,
        timeout_ms: i64,
        work: *mut *mut RawWork,
    ) -> *mut c_char;
    fn trainer_c10d_broadcast(group: *mut RawGroup, tensor: *mut c_void, root: c_int, timeout_ms: i64) -> *mut c_char;
    fn trainer_c10d_reduce_scatter_sum(
        group: *mut RawGroup,
        output: *mut c_void,
        input: *mut c_void,
        timeout_ms: i64,
        work: *mut *mut RawWork,
    ) -> *mut c_char;
    fn trainer_c10d_all_gather(
        group: *mut RawGroup,
        output: *mut c_void,
        input: *mut c_void,
        timeout_ms: i64,
        work: *mut *mut RawWork,
    ) -> *mut c_char;
    fn trainer_c10d_barrier(group: *mut RawGroup, timeout_ms: i64) -> *mut c_char;
    fn trainer_c10d_work_wait(work: *mut RawWork, timeout_ms: i64) -> *mut c_char;
    fn trainer_c10d_work_synchronize(work: *mut RawWork) -> *mut c_char;
    fn trainer_c10d_set_grad(param: *mut c_void, grad: *mut c_void) -> *mut c_char;
    fn trainer_c10d_work_free(work: *mut RawWork);
}

/// A failure reported by c10d (its exception message).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FfiError(pub String);

impl std::fmt::Display for FfiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// A c10d call's result.
pub type FfiResult<T> = std::result::Result<T, FfiError>;

/// Turns the shim's return value into a result, freeing the message.
fn check(message: *mut c_char) -> FfiResult<()> {
    if message.is_null() {
        return Ok(());
    }
    // SAFETY: a non-null return is a NUL-terminated string the shim malloc'd for us; we copy it
    // and free it exactly once with the shim's own free.
    let text = unsafe { CStr::from_ptr(message) }.to_string_lossy().into_owned();
    // SAFETY: as above; `message` is not used afterwards.
    unsafe { trainer_c10d_free_string(message) };
    Err(FfiError(text))
}

fn c_string(value: &str) -> FfiResult<CString> {
    CString::new(value).map_err(|_| FfiError(format!("{value:?} contains a NUL byte")))
}

/// The raw `at::Tensor*` tch holds for `tensor`.
fn raw(tensor: &Tensor) -> *mut c_void {
    tensor.as_ptr() as *mut c_void
}

/// A `c10d::TCPStore`, optionally behind a `c10d::PrefixStore`.
pub struct Store(*mut RawStore);

// SAFETY: c10d stores are used from several threads by c10d itself (they are shared with the
// process group's threads); the handle is only an owning pointer.
unsafe impl Send for Store {}
// SAFETY: as above: TCPStore's methods are internally synchronized.
unsafe impl Sync for Store {}

impl Store {
    /// Connects to (or, with `is_server`, hosts) the store at `host:port`.
    pub fn new(
        host: &str,
        port: u16,
        is_server: bool,
        world_size: usize,
        timeout_ms: i64,
        prefix: Option<&str>,
    ) -> FfiResult<Self> {
        let host = c_string(host)?;
        let prefix = prefix.map(c_string).transpose()?;
        let mut out = std::ptr::null_mut();
        // SAFETY: the strings outlive the call; `out` is written only on success.
        check(unsafe {
            trainer_c10d_store_new(
                host.as_ptr(),
                port,
                c_int::from(is_server),
                world_size as i64,
                timeout_ms,
                prefix.as_ref().map_or(std::ptr::null(), |p| p.as_ptr()),
                &mut out,
            )
        })?;
        Ok(Self(out))
    }

    /// Sets `key` to `value`.
    pub fn set(&self, key: &str, value: &[u8]) -> FfiResult<()> {
        let key = c_string(key)?;
        // SAFETY: the store is alive (owned by self); key and value outlive the call.
        check(unsafe { trainer_c10d_store_set(self.0, key.as_ptr(), value.as_ptr(), value.len()) })
    }

    /// Waits up to `timeout_ms` for `key` and returns its value.
    pub fn get(&self, key: &str, timeout_ms: i64) -> FfiResult<Vec<u8>> {
        let key = c_string(key)?;
        let mut value = std::ptr::null_mut();
        let mut len = 0usize;
        // SAFETY: the store is alive; on success the shim malloc'd `len` bytes at `value`.
        check(unsafe { trainer_c10d_store_get(self.0, key.as_ptr(), timeout_ms, &mut value, &mut len) })?;
        // SAFETY: `value` points to `len` initialised bytes that we copy and then free once.
        let bytes = unsafe { std::slice::from_raw_parts(value, len) }.to_vec();
        // SAFETY: as above.
        unsafe { trainer_c10d_free_bytes(value) };
        Ok(bytes)
    }

    /// Whether `key` is set.
    pub fn check(&self, key: &str) -> FfiResult<bool> {
        let key = c_string(key)?;
        let mut present = 0;
        // SAFETY: the store is alive; `present` is a valid out-pointer.
        check(unsafe { trainer_c10d_store_check(self.0, key.as_ptr(), &mut present) })?;
        Ok(present != 0)
    }
}

impl Drop for Store {
    fn drop(&mut self) {
        // SAFETY: we own the handle and drop it once.
        unsafe { trainer_c10d_store_free(self.0) }
    }
}

/// Which c10d backend a [`Group`] runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// `ProcessGroupGloo` (CPU tensors).
    Gloo,
    /// `ProcessGroupNCCL` (CUDA tensors).
    Nccl,
}

/// A c10d process group (its backend object).
pub struct Group(*mut RawGroup);

// SAFETY: c10d backends are thread-safe for issuing collectives; the handle only owns a pointer.
unsafe impl Send for Group {}

/// A collective in flight.
pub struct Work(*mut RawWork);

impl Work {
    /// Waits for the collective to finish (up to `timeout_ms`).
    pub fn wait(self, timeout_ms: i64) -> FfiResult<()> {
        // SAFETY: the work object is alive until self drops after this call.
        check(unsafe { trainer_c10d_work_wait(self.0, timeout_ms) })
    }

    /// Makes the calling thread's current device stream wait for the collective, without
    /// blocking the host (NCCL); for CPU work it does nothing: use [`Self::wait`] there.
    pub fn synchronize(self) -> FfiResult<()> {
        // SAFETY: the work object is alive until self drops after this call.
        check(unsafe { trainer_c10d_work_synchronize(self.0) })
    }
}

impl Drop for Work {
    fn drop(&mut self) {
        // SAFETY: we own the handle and drop it once.
        unsafe { trainer_c10d_work_free(self.0) }
    }
}

/// Makes `grad` the gradient tensor of `param` (same shape, dtype and device, checked): the
/// autograd engine then accumulates `param`'s gradients into it in place, so a view into a flat
/// buffer receives them. Fails when the two do not match.
pub fn set_grad(param: &Tensor, grad: &Tensor) -> FfiResult<()> {
    // SAFETY: both handles are alive for the call; the parameter keeps its own reference to
    // `grad`'s implementation (an at::Tensor copy), so `grad` may drop afterwards.
    check(unsafe { trainer_c10d_set_grad(raw(param), raw(grad)) })
}

/// Whether this build has ProcessGroupNCCL.
pub fn has_nccl() -> bool {
    // SAFETY: no arguments, no state.
    unsafe { trainer_c10d_has_nccl() != 0 }
}

/// `(free, total)` bytes of CUDA device `index`, or None without CUDA.
pub fn cuda_mem_get_info(index: usize) -> Option<(u64, u64)> {
    let (mut free, mut total) = (0u64, 0u64);
    // SAFETY: valid out-pointers; the shim returns -1 where CUDA is absent.
    let status = unsafe { trainer_c10d_cuda_mem_get_info(index as c_int, &mut free, &mut total) };
    (status == 0).then_some((free, total))
}

/// Peak bytes `(allocated, reserved)` of libtorch's CUDA caching allocator on device `index`
/// since the start or the last reset (`reset` resets them after reading); None without CUDA.
pub fn cuda_memory_peaks(index: usize, reset: bool) -> Option<(u64, u64)> {
    let (mut allocated, mut reserved) = (0u64, 0u64);
    // SAFETY: valid out-pointers; the shim catches every exception and returns -1 without CUDA.
    let status =
        unsafe { trainer_c10d_cuda_memory_peaks(index as c_int, &mut allocated, &mut reserved, c_int::from(reset)) };
    (status == 0).then_some((allocated, reserved))
}

impl Group {
    /// Creates the backend over `store` (a rendezvous with every other rank, up to `timeout_ms`).
    pub fn new(backend: Backend, store: &Store, rank: usize, size: usize, timeout_ms: i64) -> FfiResult<Self> {
        let mut out = std::ptr::null_mut();
        let (rank, size) = (rank as c_int, size as c_int);
        // SAFETY: the store is alive for the call (the backend keeps its own reference to it).
        check(unsafe {
            match backend {
                Backend::Gloo => trainer_c10d_gloo_new(store.0, rank, size, timeout_ms, &mut out),
                Backend::Nccl => trainer_c10d_nccl_new(store.0, rank, size, timeout_ms, &mut out),
            }
        })?;
        Ok(Self(out))
    }

    /// Starts an in-place sum over ranks of `tensor`.
    pub fn allreduce_sum(&self, tensor: &Tensor, timeout_ms: i64) -> FfiResult<Work> {
        let mut work = std::ptr::null_mut();
        // SAFETY: the group and tensor are alive; the backend keeps its own reference to the tensor's
        // storage until the work completes.
        check(unsafe { trainer_c10d_allreduce_sum(self.0, raw(tensor), timeout_ms, &mut work) })?;
        Ok(Work(work))
    }

    /// Broadcasts `tensor` from `root` in place.
    pub fn broadcast(&self, tensor: &Tensor, root: usize, timeout_ms: i64) -> FfiResult<()> {
        // SAFETY: the group and tensor are alive for the (blocking) call.
        check(unsafe { trainer_c10d_broadcast(self.0, raw(tensor), root as c_int, timeout_ms) })
    }

    /// Starts `output` (1/N of `input`'s length) = this rank's slice of the sum over ranks.
    pub fn reduce_scatter_sum(&self, output: &Tensor, input: &Tensor, timeout_ms: i64) -> FfiResult<Work> {
        let mut work = std::ptr::null_mut();
        // SAFETY: the group and tensors are alive; the backend holds references until completion.
        check(unsafe { trainer_c10d_reduce_scatter_sum(self.0, raw(output), raw(input), timeout_ms, &mut work) })?;
        Ok(Work(work))
    }

    /// Starts `output` (N × `input`'s length) = every rank's `input`, in rank order.
    pub fn all_gather(&self, output: &Tensor, input: &Tensor, timeout_ms: i64) -> FfiResult<Work> {
        let mut work = std::ptr::null_mut();
        // SAFETY: the group and tensors are alive; the backend holds references until completion.
        check(unsafe { trainer_c10d_all_gather(self.0, raw(output), raw(input), timeout_ms, &mut work) })?;
        Ok(Work(work))
    }

    /// Waits until every rank arrives.
    pub fn barrier(&self, timeout_ms: i64) -> FfiResult<()> {
        // SAFETY: the group is alive for the (blocking) call.
        check(unsafe { trainer_c10d_barrier(self.0, timeout_ms) })
    }
}

impl Drop for Group {
    fn drop(&mut self) {
        // SAFETY: we own the handle and drop it once.
        unsafe { trainer_c10d_group_free(self.0) }
    }
}
