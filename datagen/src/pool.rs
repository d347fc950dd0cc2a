//! Pools of image-sized buffers reused across frames and views. Allocated anew for every view,
//! such buffers cost the kernel's clearing of fresh pages (about 10 % of `datagen pairs`' CPU
//! when each view took ~40 MB of new memory).

use std::sync::{Mutex, PoisonError};

/// Buffers of dropped owners; at most as many as owners were ever alive at once.
pub struct Pool<T>(Mutex<Vec<T>>);

impl<T: Default> Pool<T> {
    /// An empty pool.
    pub const fn new() -> Self {
        Self(Mutex::new(Vec::new()))
    }

    /// A buffer given back earlier (its contents as they were left), or a new default one.
    pub fn take(&self) -> T {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).pop().unwrap_or_default()
    }

    /// Gives `buffer` back for the next owner.
    pub fn give(&self, buffer: T) {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).push(buffer);
    }
}
