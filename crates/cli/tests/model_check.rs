//! `vcedit model check` end to end on the tiny fixture models, a hub-cache layout and broken folders.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use testkit::paths::repo;

fn fixture(name: &str) -> PathBuf {
    repo().join("fixtures/models").join(name)
}

struct Run {
    code: i32,
    stdout: String,
    stderr: String,
}

fn vcedit(args: &[&str]) -> Run {
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .output()
        .unwrap();
    Run {
        code: out.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

fn check(dir: &Path) -> Run {
    vcedit(&["model", "check", dir.to_str().unwrap()])
}

fn copy_dir(src: &Path, dst: &Path) {
    fs::create_dir_all(dst).unwrap();
    for entry in fs::read_dir(src).unwrap() {
        let entry = entry.unwrap();
        let target = dst.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            fs::copy(entry.path(), &target).unwrap();
        }
    }
}

/// Builds `models--org--name` with blobs, one snapshot of symlinks and refs/main, as huggingface_hub does.
fn hub_cache(src: &Path, cache: &Path, rev: &str) -> PathBuf {
    let repo_dir = cache.join("models--org--tiny");
    let blobs = repo_dir.join("blobs");
    let snapshot = repo_dir.join("snapshots").join(rev);
    fs::create_dir_all(&blobs).unwrap();
    fs::create_dir_all(repo_dir.join("refs")).unwrap();
    fs::write(repo_dir.join("refs/main"), rev).unwrap();
    fn link_all(src: &Path, rel: &Path, blobs: &Path, snapshot: &Path, counter: &mut usize) {
        for entry in fs::read_dir(src.join(rel)).unwrap() {
            let entry = entry.unwrap();
            let rel_path = rel.join(entry.file_name());
            if entry.file_type().unwrap().is_dir() {
                link_all(src, &rel_path, blobs, snapshot, counter);
                continue;
            }
            *counter += 1;
            let blob = format!("{:040x}", *counter);
            fs::copy(entry.path(), blobs.join(&blob)).unwrap();
            let link = snapshot.join(&rel_path);
            fs::create_dir_all(link.parent().unwrap()).unwrap();
            // snapshots/<rev>/<a>/<b> -> ../../../blobs/<blob> (one ".." per directory level).
            let depth = rel_path.components().count() + 1;
            let mut target = PathBuf::new();
            for _ in 0..depth {
                target.push("..");
            }
            target.push("blobs");
            target.push(&blob);
            std::os::unix::fs::symlink(&target, &link).unwrap();
        }
    }
    let mut counter = 0;
    link_all(src, Path::new(""), &blobs, &snapshot, &mut counter);
    repo_dir
}

#[test]
fn tiny_lcm_loads_and_is_summarised() {
    let r = check(&fixture("tiny-lcm"));
    assert_eq!(r.code, 0, "{}{}", r.stdout, r.stderr);
    for expected in [
        "pipeline     LatentConsistencyModelPipeline",
        "unet         UNet2DConditionModel",
        "LCM time condition 16",
        "text_encoder CLIPTextModel",
        "QuickGelu",
        "vae          AutoencoderKL",
        "tokenizer    CLIP BPE from vocab.json + merges.txt - 720 tokens, 77 positions, pad \"<|endoftext|>\"",
        "scheduler    LCMScheduler",
        "15 steps (diffusers 0.22) = [999, 939, 879, 819, 759, 699, 639, 579, 519, 459, 399, 339, 279, 219, 159]",
        "OK: all components load",
        "(f32)",
        // What --size must be, as `edit` checks it (a 4× codec, two UNet downsamplings).
        "sizes        --size: multiples of 16 (4× codec, 2 UNet downsamplings); trained at 64×64",
    ] {
        assert!(r.stdout.contains(expected), "missing {expected:?} in\n{}", r.stdout);
    }
}

#[test]
fn tiny_ip2p_with_f16_weights_and_tokenizer_json() {
    let r = check(&fixture("tiny-ip2p"));
    assert_eq!(r.code, 0, "{}{}", r.stdout, r.stderr);
    for expected in [
        "StableDiffusionInstructPix2PixPipeline",
        "in 8 / out 4 channels",
        "(f16)",
        "CLIP BPE from tokenizer.json",
        "pad \"!\"",
        "model_max_length 1e30 ignored",
        "DDIMScheduler",
    ] {
        assert!(
            r.stdout.contains(expected),
            "missing {expected:?} in\n{}",
            r.stdout
        );
    }
}

#[test]
fn hub_cache_folder_and_snapshot_both_work() {
    let tmp = tempfile::tempdir().unwrap();
    let repo_dir = hub_cache(&fixture("tiny-lcm"), tmp.path(), "0123abcd");
    let r = check(&repo_dir);
    assert_eq!(r.code, 0, "{}{}", r.stdout, r.stderr);
    assert!(r.stdout.contains("snapshots/0123abcd"), "{}", r.stdout);
    let r = check(&repo_dir.join("snapshots/0123abcd"));
    assert_eq!(r.code, 0, "{}{}", r.stdout, r.stderr);

    // A blob that vanished shows as a broken link, not as a generic read error.
    let link = repo_dir.join("snapshots/0123abcd/vae/diffusion_pytorch_model.safetensors");
    let blob = link.parent().unwrap().join(fs::read_link(&link).unwrap());
    fs::remove_file(blob).unwrap();
    let r = check(&repo_dir);
    assert_eq!(r.code, 1);
    assert!(
        r.stderr
            .contains("vae/diffusion_pytorch_model.safetensors is a broken link"),
        "{}",
        r.stderr
    );
}

#[test]
fn broken_folder_gives_one_line_listing_everything_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("broken");
    copy_dir(&fixture("tiny-lcm"), &dir);
    fs::remove_file(dir.join("unet/config.json")).unwrap();
    fs::remove_file(dir.join("vae/diffusion_pytorch_model.safetensors")).unwrap();
    fs::remove_file(dir.join("tokenizer/merges.txt")).unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1, "{}", r.stdout);
    assert!(r.stdout.is_empty());
    let line = r.stderr.trim_end();
    assert_eq!(line.lines().count(), 1, "{line}");
    assert!(
        line.contains(
            "is incomplete: missing unet/config.json, vae/diffusion_pytorch_model.safetensors, tokenizer/merges.txt"
        ),
        "{line}"
    );
}

#[test]
fn pickles_variants_and_mismatches_are_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("m");
    copy_dir(&fixture("tiny-lcm"), &dir);

    // Only an fp16-variant file: accepted and named.
    fs::rename(
        dir.join("unet/diffusion_pytorch_model.safetensors"),
        dir.join("unet/diffusion_pytorch_model.fp16.safetensors"),
    )
    .unwrap();
    let r = vcedit(&["model", "check", dir.to_str().unwrap(), "--headers-only"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("fp16 variant"), "{}", r.stdout);
    assert!(r.stdout.contains("models not built"), "{}", r.stdout);

    // A pickle instead of safetensors is refused with advice.
    fs::rename(
        dir.join("vae/diffusion_pytorch_model.safetensors"),
        dir.join("vae/diffusion_pytorch_model.bin"),
    )
    .unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1);
    assert!(
        r.stderr
            .contains("vae/diffusion_pytorch_model.bin is a PyTorch pickle"),
        "{}",
        r.stderr
    );
    assert!(
        r.stderr.contains("convert it to .safetensors"),
        "{}",
        r.stderr
    );
    fs::rename(
        dir.join("vae/diffusion_pytorch_model.bin"),
        dir.join("vae/diffusion_pytorch_model.safetensors"),
    )
    .unwrap();

    // A UNet config that disagrees with the text encoder and the VAE.
    let path = dir.join("unet/config.json");
    let mut cfg: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
    cfg["cross_attention_dim"] = 64.into();
    cfg["out_channels"] = 3.into();
    fs::write(&path, cfg.to_string()).unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1);
    assert_eq!(r.stderr.trim_end().lines().count(), 1);
    for expected in [
        "has inconsistent files",
        "cross_attention_dim 64 does not match the text encoder's hidden_size 32",
        "out_channels 3 differs from the VAE's latent_channels 4",
        "conv_out.weight has shape [4, 16, 3, 3]",
    ] {
        assert!(
            r.stderr.contains(expected),
            "missing {expected:?} in {}",
            r.stderr
        );
    }

    // A truncated weight file.
    fs::write(
        &path,
        fs::read(fixture("tiny-lcm").join("unet/config.json")).unwrap(),
    )
    .unwrap();
    let weights = dir.join("text_encoder/model.safetensors");
    let bytes = fs::read(&weights).unwrap();
    fs::write(&weights, &bytes[..bytes.len() / 2]).unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1);
    assert!(
        r.stderr.contains("text_encoder/model.safetensors"),
        "{}",
        r.stderr
    );
    assert!(r.stderr.contains("truncated download"), "{}", r.stderr);
}

#[test]
fn missing_folder_is_one_clear_error() {
    let r = check(Path::new("/nonexistent/model"));
    assert_eq!(r.code, 1);
    assert_eq!(
        r.stderr.trim_end(),
        "error: model folder /nonexistent/model does not exist"
    );
}

/// A NaN in the weights is named with its place (the element, counted from 0), and a tokenizer folder
/// with neither form names both (tokenizer.json or vocab.json + merges.txt).
#[test]
fn a_nan_and_a_missing_tokenizer_are_named_plainly() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("model");
    copy_dir(&fixture("tiny-lcm"), &dir);
    // The alphabetically first f32 tensor of the VAE gets a NaN at element 3.
    let weights = dir.join("vae/diffusion_pytorch_model.safetensors");
    let mut bytes = fs::read(&weights).unwrap();
    let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + header_len]).unwrap();
    let (name, start) = header
        .as_object()
        .unwrap()
        .iter()
        .filter(|(name, t)| *name != "__metadata__" && t["dtype"] == "F32")
        .map(|(name, t)| {
            (
                name.clone(),
                t["data_offsets"][0].as_u64().unwrap() as usize,
            )
        })
        .min()
        .unwrap();
    let at = 8 + header_len + start + 3 * 4;
    bytes[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    fs::write(&weights, &bytes).unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1, "{}", r.stderr);
    assert!(
        r.stderr.contains(&format!(
            "tensor {name} holds a NaN or an infinity (the first at element 3, counting from 0)"
        )),
        "{}",
        r.stderr
    );

    copy_dir(&fixture("tiny-lcm"), &dir);
    fs::remove_file(dir.join("tokenizer/vocab.json")).unwrap();
    fs::remove_file(dir.join("tokenizer/merges.txt")).unwrap();
    let r = check(&dir);
    assert_eq!(r.code, 1);
    assert!(
        r.stderr
            .contains("missing tokenizer/tokenizer.json (or vocab.json + merges.txt)"),
        "{}",
        r.stderr
    );
}
