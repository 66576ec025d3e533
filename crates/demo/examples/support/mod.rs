//! What the demo studies in this folder share: a demo run's guidance images and the editing fit's
//! trainer on the demo scene.

use std::path::{Path, PathBuf};

use demo::run::DemoScene;
use edit::fit::{EditTrainer, TrainSettings};
use splat::Image;

/// The guidance images in `dir` (a demo run's `iter_K/guidance`), in file-name order.
pub fn guidance(dir: &Path) -> Result<Vec<Image>, Box<dyn std::error::Error>> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()?;
    paths.sort();
    Ok(paths
        .iter()
        .map(|p| Image::load(p))
        .collect::<Result<_, _>>()?)
}

/// The editing fit's trainer on the demo scene as `vcedit demo` starts it (the scene's mask, the
/// cameras' extent, the source's background), with densification off unless `densify`.
pub fn edit_trainer(scene: &DemoScene, mut settings: TrainSettings, densify: bool) -> EditTrainer {
    if !densify {
        settings.strategy.densify_from = u64::MAX;
    }
    EditTrainer::new(
        &scene.built.scene,
        Some(scene.mask.clone()),
        settings,
        edit::run::scene_extent(&scene.cameras),
        scene.source.background,
    )
}
