//! CLIP image/text embeddings and the directional similarity against transformers' `CLIPModel`
//! (a tiny random model; fixtures from tools/make_clip_fixtures.py).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use edit::eval::clip_score::ClipModel;
use serde_json::Value;
use splat::Image;
use testkit::diff::max_abs_diff;

const TOL: f32 = 1e-4;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/clip")
}

struct Fixture {
    meta: Value,
    tensors: HashMap<String, Tensor>,
    model: ClipModel,
}

fn load() -> Fixture {
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(fixtures().join("cases.json")).unwrap())
            .unwrap();
    let tensors =
        candle_core::safetensors::load(fixtures().join("cases.safetensors"), &Device::Cpu).unwrap();
    let model = ClipModel::load(&fixtures().join("tiny-clip")).unwrap();
    Fixture {
        meta,
        tensors,
        model,
    }
}

impl Fixture {
    fn vec_f32(&self, key: &str) -> Vec<f32> {
        self.tensors[key]
            .flatten_all()
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap()
            .to_vec1()
            .unwrap()
    }

    fn image(&self, tag: &str, k: usize) -> Image {
        let t = &self.tensors[&format!("{tag}_{k}_image")];
        let (h, w, c) = t.dims3().unwrap();
        Image::from_data(
            w as u32,
            h as u32,
            c as u32,
            self.vec_f32(&format!("{tag}_{k}_image")),
        )
    }

    fn views(&self) -> usize {
        self.meta["views"].as_array().unwrap().len()
    }

    fn prompts(&self) -> Vec<String> {
        self.meta["prompts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p.as_str().unwrap().to_string())
            .collect()
    }
}

#[test]
fn preprocessing_matches_clip_image_processor() {
    let f = load();
    for k in 0..f.views() {
        for tag in ["source", "edited"] {
            let got = f.model.preprocess().apply(&f.image(tag, k)).unwrap();
            let want = f.vec_f32(&format!("{tag}_{k}_pixel_values"));
            let d = max_abs_diff(&got, &want);
            assert!(d < TOL, "view {k} {tag}: pixel values differ by {d}");
        }
    }
}

#[test]
fn image_embeddings_match_transformers() {
    let f = load();
    // From the reference pixel values (the tower alone) and from the images (preprocessing + tower).
    for k in 0..f.views() {
        let pixels = f.tensors[&format!("source_{k}_pixel_values")]
            .unsqueeze(0)
            .unwrap();
        let from_pixels = f.model.image_features_from_pixels(&pixels).unwrap();
        let want = f.vec_f32(&format!("source_{k}_embeds"));
        let d = max_abs_diff(&from_pixels[0], &want);
        assert!(
            d < TOL,
            "view {k}: embedding from pixel values differs by {d}"
        );
    }
    let images: Vec<Image> = (0..f.views()).map(|k| f.image("edited", k)).collect();
    let refs: Vec<&Image> = images.iter().collect();
    let got = f.model.image_features(&refs).unwrap();
    for (k, g) in got.iter().enumerate() {
        let want = f.vec_f32(&format!("edited_{k}_embeds"));
        let d = max_abs_diff(g, &want);
        assert!(d < TOL, "view {k}: embedding from image differs by {d}");
    }
}

#[test]
fn text_ids_and_embeddings_match_transformers() {
    let f = load();
    let prompts = f.prompts();
    let ids = f.tensors["text_ids"].to_vec2::<i64>().unwrap();
    for (p, want) in prompts.iter().zip(&ids) {
        let got = f.model.tokenizer().encode(p).ids;
        let want: Vec<u32> = want.iter().map(|&v| v as u32).collect();
        assert_eq!(got, want, "ids of {p:?}");
    }
    let refs: Vec<&str> = prompts.iter().map(String::as_str).collect();
    let got = f.model.text_features(&refs).unwrap();
    let want = f.tensors["text_embeds"].to_vec2::<f32>().unwrap();
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        let d = max_abs_diff(g, w);
        assert!(d < TOL, "prompt {k}: text embedding differs by {d}");
    }
}

#[test]
fn directional_similarity_matches_reference() {
    let f = load();
    let prompts = f.prompts();
    let want: Vec<f64> = f.tensors["directional"].to_vec1().unwrap();
    let mut all = Vec::new();
    for (k, view) in f.meta["views"].as_array().unwrap().iter().enumerate() {
        let s = &prompts[view["source_prompt"].as_u64().unwrap() as usize];
        let t = &prompts[view["target_prompt"].as_u64().unwrap() as usize];
        let (src, edt) = (f.image("source", k), f.image("edited", k));
        let r = f
            .model
            .directional_similarity(&[&src], &[&edt], s, t)
            .unwrap();
        assert!(
            (r.directional - want[k]).abs() < f64::from(TOL),
            "view {k}: {} vs {}",
            r.directional,
            want[k]
        );
        all.push(r.directional);
    }
    // The batched call over views sharing a prompt pair averages the same per-view values.
    let views = [0usize, 2];
    let src: Vec<Image> = views.iter().map(|&k| f.image("source", k)).collect();
    let edt: Vec<Image> = views.iter().map(|&k| f.image("edited", k)).collect();
    let r = f
        .model
        .directional_similarity(
            &src.iter().collect::<Vec<_>>(),
            &edt.iter().collect::<Vec<_>>(),
            &prompts[0],
            &prompts[1],
        )
        .unwrap();
    assert_eq!(r.per_view.len(), 2);
    assert!((r.directional - (want[0] + want[2]) / 2.0).abs() < f64::from(TOL));
    // An unchanged image has no direction: the similarity is 0 (torch's clamped cosine of a zero vector).
    let same = f.image("source", 0);
    let r = f
        .model
        .directional_similarity(&[&same], &[&same], &prompts[0], &prompts[1])
        .unwrap();
    assert_eq!(r.directional, 0.0);
    assert!((r.image_similarity - 1.0).abs() < 1e-9);
}

#[test]
fn broken_folders_are_reported_with_their_path() {
    let dir = tempfile::tempdir().unwrap();
    let err = ClipModel::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("config.json"), "{err}");
    std::fs::write(dir.path().join("config.json"), r#"{"text_config": {}}"#).unwrap();
    let err = ClipModel::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("vision_config"), "{err}");
    // A complete config without weights names what is missing.
    let src = fixtures().join("tiny-clip");
    for name in [
        "config.json",
        "vocab.json",
        "merges.txt",
        "tokenizer_config.json",
    ] {
        std::fs::copy(src.join(name), dir.path().join(name)).unwrap();
    }
    let err = ClipModel::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("safetensors"), "{err}");
}
