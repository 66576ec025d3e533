//! One module per subcommand.
pub mod bench;
pub mod convert;
pub mod demo;
pub mod demo_model;
pub mod edit;
pub mod edit_image;
pub mod fit;
pub mod inspect;
pub mod metrics;
pub mod model;
pub mod render;
pub mod view;
