//! The demo model inside the binary: `vcedit demo` works from any folder with the binary alone (after
//! `cargo install`, or copied elsewhere), without the checkout it was built from. The files (about 17 MB)
//! are written once into the user's cache folder and loaded from there like any
//! model folder, so the loader needs no second, in-memory path.

#[cfg(feature = "embedded-demo-model")]
use std::path::Path;
use std::path::PathBuf;

#[cfg(feature = "embedded-demo-model")]
use anyhow::Context;
use anyhow::Result;

/// `(path inside the model folder, contents)`, from `models/demo` at build time.
#[cfg(feature = "embedded-demo-model")]
macro_rules! embed {
    ($name:literal) => {
        (
            $name,
            include_bytes!(concat!("../../../models/demo/", $name)) as &[u8],
        )
    };
}

#[cfg(feature = "embedded-demo-model")]
const FILES: &[(&str, &[u8])] = &[
    embed!("model_index.json"),
    embed!("scheduler/scheduler_config.json"),
    embed!("text_encoder/config.json"),
    embed!("text_encoder/model.safetensors"),
    embed!("tokenizer/merges.txt"),
    embed!("tokenizer/special_tokens_map.json"),
    embed!("tokenizer/tokenizer_config.json"),
    embed!("tokenizer/vocab.json"),
    embed!("unet/config.json"),
    embed!("unet/diffusion_pytorch_model.safetensors"),
    embed!("vae/config.json"),
    embed!("vae/diffusion_pytorch_model.safetensors"),
];

/// Marks a folder whose files were all written (a run killed while extracting leaves none).
#[cfg(feature = "embedded-demo-model")]
const COMPLETE: &str = ".complete";

/// FNV-1a over the names and contents: a new model gets a new folder.
#[cfg(feature = "embedded-demo-model")]
fn fingerprint() -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for (name, bytes) in FILES {
        for &b in name.as_bytes().iter().chain(*bytes) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    }
    h
}

/// The embedded demo model as a folder, written on first use.
#[cfg(feature = "embedded-demo-model")]
pub fn demo_model() -> Result<PathBuf> {
    let dir = files::cache_dir().join(format!("demo-model-{:016x}", fingerprint()));
    if dir.join(COMPLETE).is_file() {
        return Ok(dir);
    }
    extract(&dir)
        .with_context(|| format!("writing the built-in demo model to {}", dir.display()))?;
    Ok(dir)
}

/// Built without the embedded model: `models/demo` of the current folder (a checkout).
#[cfg(not(feature = "embedded-demo-model"))]
pub fn demo_model() -> Result<PathBuf> {
    let local = PathBuf::from("models/demo");
    if local.join("model_index.json").is_file() {
        return Ok(local);
    }
    anyhow::bail!(
        "this vcedit was built without its demo model (feature embedded-demo-model) and there is no \
         ./models/demo; pass --model DIR"
    )
}

#[cfg(feature = "embedded-demo-model")]
fn extract(dir: &Path) -> Result<()> {
    for (name, bytes) in FILES {
        let path = dir.join(name);
        std::fs::create_dir_all(path.parent().unwrap_or(dir))?;
        files::atomic_write(&path, bytes)?;
    }
    files::atomic_write(&dir.join(COMPLETE), b"")?;
    Ok(())
}

#[cfg(all(test, feature = "embedded-demo-model"))]
mod tests {
    use super::*;

    /// Every file of the committed demo model is embedded (a file added there must be added here).
    #[test]
    fn embeds_every_file_of_the_demo_model() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
        let mut on_disk = Vec::new();
        let mut stack = vec![root.clone()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else if p.file_name().is_some_and(|n| n != "README.md") {
                    on_disk.push(
                        p.strip_prefix(&root)
                            .unwrap()
                            .to_string_lossy()
                            .replace('\\', "/"),
                    );
                }
            }
        }
        on_disk.sort();
        let embedded: Vec<String> = FILES.iter().map(|(n, _)| n.to_string()).collect();
        assert_eq!(embedded, on_disk);
    }
}
