//! The comparison's reference rows: renders of one scene agree across views up to resampling, and the
//! autoencoder round trip adds error (the floor every guidance image is subject to).

use std::path::PathBuf;

use demo::run::{demo_scene, load_model, reference_rows, reference_table, DemoOptions};

#[test]
fn renders_are_consistent_and_the_codec_adds_a_floor() {
    let model_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
    let model = load_model(&model_dir).expect("the committed demo model");
    let mut opts = DemoOptions::new(model_dir, std::env::temp_dir());
    opts.views = 6;
    opts.size = 64;
    let scene = demo_scene(&opts).unwrap();
    let rows = reference_rows(&opts, &model, &scene).unwrap();
    println!("{}", reference_table(&rows));
    let get = |name: &str| rows.iter().find(|r| r.name == name).unwrap();
    let (source, source_codec) = (get("source renders"), get("source through the autoencoder"));
    let (ideal, ideal_codec) = (
        get("ideal edit (target renders)"),
        get("ideal edit through the autoencoder"),
    );
    // A solid red sphere: warping its renders into each other leaves only resampling error.
    assert!(source.object.unwrap() < 0.01, "{rows:?}");
    assert!(ideal.object.unwrap() < 0.01, "{rows:?}");
    assert!(source.whole.unwrap() < 0.01, "{rows:?}");
    for (exact, coded) in [(source, source_codec), (ideal, ideal_codec)] {
        assert!(
            coded.object.unwrap() > exact.object.unwrap() + 0.003,
            "{rows:?}"
        );
        assert!(
            coded.whole.unwrap() > exact.whole.unwrap() + 0.003,
            "{rows:?}"
        );
    }
}
