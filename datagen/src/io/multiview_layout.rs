//! Where the multi-camera layouts were named and read before the one layout registry
//! ([`crate::io::layout`]); these paths stay valid for the callers that still use them.

pub use crate::io::layout::{MultiViewLayoutName, detect_multiview_layout, read_multiview_as};
