//! The small types the seam's ops take as arguments (an activation's kind, what a convolution adds to its
//! output), apart from `device.rs` so that the backends' bodies (`cpu.rs`, `gpu/`) and the seam that
//! dispatches to them import them without importing each other.

/// The activation functions with a kernel of their own (beside candle-nn's [`Activation`](candle_nn::Activation)s).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unary {
    Relu,
    Silu,
    Tanh,
    /// Exact (erf) GELU.
    GeluErf,
    /// tanh-approximated GELU.
    GeluTanh,
    /// `x·σ(1.702·x)` (CLIP ViT-L).
    QuickGelu,
}

/// What a convolution adds to its output besides its bias. A backend may add it in the pass that adds
/// the bias (the GPU does: one pass over the output instead of two).
#[derive(Debug)]
pub enum Addend<'a, T> {
    None,
    /// [batch, out channels, h, w]: a skip connection.
    Residual(&'a T),
    /// [batch, out channels]: one value per image and channel (a ResNet's time embedding).
    PerChannel(&'a T),
}

impl<'a, T> Addend<'a, T> {
    /// The added tensor, if any.
    pub(crate) fn term(self) -> Option<&'a T> {
        match self {
            Addend::None => None,
            Addend::Residual(t) | Addend::PerChannel(t) => Some(t),
        }
    }

    /// The same kind of addend with `u` as its tensor (a backend's own tensor for the dispatched one).
    pub(crate) fn with<U>(self, u: &U) -> Addend<'_, U> {
        match self {
            Addend::None => Addend::None,
            Addend::Residual(_) => Addend::Residual(u),
            Addend::PerChannel(_) => Addend::PerChannel(u),
        }
    }
}

impl<T> Clone for Addend<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for Addend<'_, T> {}
