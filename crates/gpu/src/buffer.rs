//! The one form in which the engines hand GPU data to each other: f32 values in a device buffer, with
//! their count. A raw cubecl `Handle` says neither what it holds nor how much of it counts (a pooled
//! buffer may be larger than its contents); this type says both, and is checked once where it is made.

use cubecl::server::Handle;

/// `len` f32 values on the device the buffer was made on (the first `len` of a buffer at least that
/// long). Cloning shares the buffer, as cubecl handles do.
#[derive(Clone)]
pub struct F32Buffer {
    handle: Handle,
    len: usize,
}

impl std::fmt::Debug for F32Buffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "F32Buffer[{}]", self.len)
    }
}

/// A buffer smaller than the values it is said to hold.
#[derive(Debug, thiserror::Error)]
#[error("a {bytes} byte GPU buffer cannot hold {len} f32 values")]
pub struct BufferTooSmall {
    pub bytes: u64,
    pub len: usize,
}

impl F32Buffer {
    /// The first `len` f32 values of `handle`'s buffer.
    pub fn new(handle: Handle, len: usize) -> Result<Self, BufferTooSmall> {
        let bytes = handle.size_in_used();
        if bytes < (len * std::mem::size_of::<f32>()) as u64 {
            return Err(BufferTooSmall { bytes, len });
        }
        Ok(Self { handle, len })
    }

    /// How many f32 values it holds.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The bytes its values take on the device.
    pub fn bytes(&self) -> u64 {
        (self.len * std::mem::size_of::<f32>()) as u64
    }

    /// The buffer, for a kernel launch.
    pub fn handle(&self) -> &Handle {
        &self.handle
    }

    pub fn into_handle(self) -> Handle {
        self.handle
    }
}

/// f32 values on the host or in a buffer on the GPU both engines share: what one engine hands the other
/// when its data may live on either side (the networks' attention maps to the lifting, the render-backs
/// back), so nothing already on the device is read back to be uploaded again.
#[derive(Clone, Debug)]
pub enum F32Values {
    Host(Vec<f32>),
    Device(F32Buffer),
}

impl F32Values {
    /// How many values.
    pub fn len(&self) -> usize {
        match self {
            F32Values::Host(values) => values.len(),
            F32Values::Device(buffer) => buffer.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether the values are in a device buffer.
    pub fn is_on_device(&self) -> bool {
        matches!(self, F32Values::Device(_))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cubecl::prelude::*;

    #[test]
    fn a_buffer_holds_what_it_says_or_is_refused() {
        let Some(ctx) = crate::testing::context_or_skip() else {
            return;
        };
        let handle = ctx
            .client
            .create_from_slice(f32::as_bytes(&[1.0, 2.0, 3.0]));
        let buffer = F32Buffer::new(handle.clone(), 3).unwrap();
        assert_eq!((buffer.len(), buffer.bytes()), (3, 12));
        assert!(
            F32Buffer::new(handle.clone(), 2).is_ok(),
            "a prefix is fine"
        );
        let err = F32Buffer::new(handle, 4).unwrap_err();
        assert!(
            err.to_string().contains("cannot hold 4 f32 values"),
            "{err}"
        );
    }
}
