//! Finding and opening Stable Diffusion model folders.
//!
//! Accepted layouts:
//! - a diffusers folder: `model_index.json` plus `unet/`, `vae/`, `text_encoder/`, `tokenizer/`, `scheduler/`;
//! - a Hugging Face hub-cache snapshot `models--org--name/snapshots/<rev>/` (files are symlinks into
//!   `../../blobs`), or the `models--org--name` folder itself, whose revision comes from `refs/main`
//!   (else the only, or most recently modified, snapshot).
//!
//! Weights are read from safetensors only (plain, `*.fp16.safetensors` variants, or sharded with a
//! `*.safetensors.index.json`), memory-mapped and converted to the requested dtype on access. PyTorch
//! pickles (`.bin`, `.ckpt`, `.pt`) are refused: unpickling runs arbitrary code.
//!
//! Problems with a folder are collected and reported together in one [`LoadError::Incomplete`], so a user
//! fixes a broken download in one go instead of one file per run.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::fs;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use serde::de::DeserializeOwned;
use serde::Deserialize;

pub use crate::weights::{read_safetensors_header, var_builder_from_files, TensorInfo};

/// Errors from resolving a model folder or reading its files. Every message names the file concerned.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("model folder {0} does not exist")]
    NotFound(PathBuf),
    #[error("model folder {} is incomplete: {}", .root.display(), ProblemList(.problems))]
    Incomplete {
        root: PathBuf,
        problems: Vec<Problem>,
    },
    #[error("model folder {} has inconsistent files: {}", .root.display(), ProblemList(.problems))]
    Inconsistent {
        root: PathBuf,
        problems: Vec<Problem>,
    },
    #[error("{}: {message}", .path.display())]
    BadFile { path: PathBuf, message: String },
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {source}", .path.display())]
    Candle {
        path: PathBuf,
        #[source]
        source: candle_core::Error,
    },
}

/// One thing wrong with a model folder; paths are relative to the model root.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Problem {
    /// A required file that is not there.
    Missing(String),
    /// A symlink whose target (a hub-cache blob) is gone.
    BrokenLink(String),
    /// Only PyTorch pickles were found where safetensors were expected.
    PickleOnly(String),
    /// A file that is present but unusable or inconsistent with another one.
    Invalid { file: String, reason: String },
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::Missing(p) => write!(f, "missing {p}"),
            Problem::BrokenLink(p) => write!(f, "{p} is a broken link (its blob is missing)"),
            Problem::PickleOnly(p) => write!(
                f,
                "{p} is a PyTorch pickle, which vcedit refuses to read (unpickling can run code); \
                 convert it to .safetensors"
            ),
            Problem::Invalid { file, reason } => write!(f, "{file}: {reason}"),
        }
    }
}

/// Formats problems on one line, gathering all missing files behind a single "missing".
struct ProblemList<'a>(&'a [Problem]);

impl fmt::Display for ProblemList<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let missing: Vec<&str> = self
            .0
            .iter()
            .filter_map(|p| match p {
                Problem::Missing(m) => Some(m.as_str()),
                _ => None,
            })
            .collect();
        let mut parts = Vec::new();
        if !missing.is_empty() {
            parts.push(format!("missing {}", missing.join(", ")));
        }
        parts.extend(
            self.0
                .iter()
                .filter(|p| !matches!(p, Problem::Missing(_)))
                .map(|p| p.to_string()),
        );
        f.write_str(&parts.join("; "))
    }
}

/// The sub-models of a Stable Diffusion pipeline folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Component {
    Unet,
    Vae,
    TextEncoder,
    Tokenizer,
    Scheduler,
}

impl Component {
    pub const ALL: [Component; 5] = [
        Component::Unet,
        Component::Vae,
        Component::TextEncoder,
        Component::Tokenizer,
        Component::Scheduler,
    ];

    /// The sub-folder name in the diffusers layout (also the key in `model_index.json`).
    pub fn folder(self) -> &'static str {
        match self {
            Component::Unet => "unet",
            Component::Vae => "vae",
            Component::TextEncoder => "text_encoder",
            Component::Tokenizer => "tokenizer",
            Component::Scheduler => "scheduler",
        }
    }

    /// The config file name inside the component folder (`None` for the tokenizer, whose files vary).
    pub fn config_file(self) -> Option<&'static str> {
        match self {
            Component::Unet | Component::Vae | Component::TextEncoder => Some("config.json"),
            Component::Scheduler => Some("scheduler_config.json"),
            Component::Tokenizer => None,
        }
    }

    /// Whether the component has weights.
    pub fn has_weights(self) -> bool {
        matches!(
            self,
            Component::Unet | Component::Vae | Component::TextEncoder
        )
    }

    /// The weight file diffusers/transformers write, named when none is found.
    pub fn default_weight_file(self) -> &'static str {
        match self {
            Component::TextEncoder => "model.safetensors",
            _ => "diffusion_pytorch_model.safetensors",
        }
    }
}

impl fmt::Display for Component {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.folder())
    }
}

/// The weight files chosen for one component.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WeightFiles {
    /// Absolute paths (symlinks not resolved), in a stable order.
    pub files: Vec<PathBuf>,
    /// `None` for plain names, `Some("fp16")` for `*.fp16.safetensors` and the like.
    pub variant: Option<String>,
    /// Whether the files come from a `*.safetensors.index.json`.
    pub sharded: bool,
}

/// A resolved model folder. [`ModelDir::open`] has checked that every needed file is present.
#[derive(Debug, Clone)]
pub struct ModelDir {
    root: PathBuf,
    /// Component folder names with their `[library, class]` from `model_index.json`.
    index: DeclaredClasses,
    pipeline_class: Option<String>,
}

#[derive(Deserialize)]
struct ShardIndex {
    weight_map: BTreeMap<String, String>,
}

impl ModelDir {
    /// Resolves `path` (diffusers folder or hub cache) and checks all five components are complete.
    pub fn open(path: impl AsRef<Path>) -> Result<ModelDir, LoadError> {
        Self::open_components(path, &Component::ALL)
    }

    /// Like [`ModelDir::open`] but only checks the given components (e.g. a UNet-only folder for tests).
    pub fn open_components(
        path: impl AsRef<Path>,
        components: &[Component],
    ) -> Result<ModelDir, LoadError> {
        let root = resolve_model_path(path.as_ref())?;
        let mut problems = Vec::new();
        let index_path = root.join("model_index.json");
        let mut index = BTreeMap::new();
        let mut pipeline_class = None;
        match file_state(&index_path) {
            FileState::Present => match read_json::<serde_json::Value>(&index_path) {
                Ok(value) => {
                    let (class, entries) = parse_model_index(&value);
                    pipeline_class = class;
                    index = entries;
                }
                Err(e) => problems.push(Problem::Invalid {
                    file: "model_index.json".into(),
                    reason: short_reason(&e),
                }),
            },
            state @ (FileState::BrokenLink | FileState::NotAFile) => {
                problems.extend(state.unusable("model_index.json".into()))
            }
            FileState::Absent => problems.push(Problem::Missing("model_index.json".into())),
        }
        let dir = ModelDir {
            root,
            index,
            pipeline_class,
        };
        for &c in components {
            problems.extend(dir.component_problems(c));
        }
        if problems.is_empty() {
            Ok(dir)
        } else {
            Err(LoadError::Incomplete {
                root: dir.root,
                problems,
            })
        }
    }

    /// The resolved folder (for a hub cache: the snapshot folder).
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// `_class_name` of `model_index.json`, e.g. `StableDiffusionPipeline`.
    pub fn pipeline_class(&self) -> Option<&str> {
        self.pipeline_class.as_deref()
    }

    /// `[library, class]` declared for a component in `model_index.json`, if any.
    pub fn declared_class(&self, component: Component) -> Option<(&str, &str)> {
        match self.index.get(component.folder()) {
            Some((Some(lib), Some(class))) => Some((lib.as_str(), class.as_str())),
            _ => None,
        }
    }

    /// The component's folder.
    pub fn component_dir(&self, component: Component) -> PathBuf {
        self.root.join(component.folder())
    }

    /// Path of the component's config file (tokenizer: `tokenizer_config.json`).
    pub fn config_path(&self, component: Component) -> PathBuf {
        self.component_dir(component)
            .join(component.config_file().unwrap_or("tokenizer_config.json"))
    }

    /// Parses the component's config file into `T`.
    pub fn read_config<T: DeserializeOwned>(&self, component: Component) -> Result<T, LoadError> {
        read_json(&self.config_path(component))
    }

    /// The safetensors files holding a component's weights.
    pub fn weight_files(&self, component: Component) -> Result<WeightFiles, LoadError> {
        find_weight_files(&self.component_dir(component))
    }

    /// A memory-mapped `VarBuilder` over a component's weights, converting on access to `dtype`.
    pub fn var_builder(
        &self,
        component: Component,
        dtype: DType,
        device: &Device,
    ) -> Result<VarBuilder<'static>, LoadError> {
        let weights = self.weight_files(component)?;
        var_builder_from_files(&weights.files, dtype, device)
    }

    /// Everything wrong with one component, as paths relative to the root.
    fn component_problems(&self, component: Component) -> Vec<Problem> {
        let mut problems = Vec::new();
        let folder = component.folder();
        let dir = self.component_dir(component);
        let rel = |name: &str| format!("{folder}/{name}");
        if !dir.is_dir() {
            problems.push(Problem::Missing(format!("{folder}/")));
            return problems;
        }
        if let Some(config) = component.config_file() {
            let path = dir.join(config);
            match file_state(&path) {
                FileState::Present => {
                    if let Err(e) = read_json::<serde_json::Value>(&path) {
                        problems.push(Problem::Invalid {
                            file: rel(config),
                            reason: short_reason(&e),
                        });
                    }
                }
                state @ (FileState::BrokenLink | FileState::NotAFile) => {
                    problems.extend(state.unusable(rel(config)))
                }
                FileState::Absent => problems.push(Problem::Missing(rel(config))),
            }
        }
        if component == Component::Tokenizer {
            problems.extend(tokenizer_problems(&dir, folder));
        }
        if component.has_weights() {
            match find_weight_files_inner(&dir) {
                Ok(weights) => {
                    for file in &weights.files {
                        if let Err(e) = read_safetensors_header(file) {
                            problems.push(Problem::Invalid {
                                file: rel(&file_name(file)),
                                reason: short_reason(&e),
                            });
                        }
                    }
                }
                Err(WeightSearchError::Problems(list)) => {
                    problems.extend(list.into_iter().map(|p| prefix_problem(p, folder)))
                }
                Err(WeightSearchError::Other(e)) => problems.push(Problem::Invalid {
                    file: format!("{folder}/"),
                    reason: short_reason(&e),
                }),
            }
        }
        problems
    }
}

/// The tokenizer needs `tokenizer.json`, or `vocab.json` together with `merges.txt`.
fn tokenizer_problems(dir: &Path, folder: &str) -> Vec<Problem> {
    let state = |name: &str| file_state(&dir.join(name));
    let mut problems = Vec::new();
    match state("tokenizer.json") {
        FileState::Present => return problems,
        state @ (FileState::BrokenLink | FileState::NotAFile) => {
            problems.extend(state.unusable(format!("{folder}/tokenizer.json")));
            return problems;
        }
        FileState::Absent => {}
    }
    // Neither form: name both, the one-file form first (what current hub folders carry).
    let pair = ["vocab.json", "merges.txt"];
    if pair.iter().all(|name| state(name) == FileState::Absent) {
        problems.push(Problem::Missing(format!(
            "{folder}/tokenizer.json (or vocab.json + merges.txt)"
        )));
        return problems;
    }
    for (name, other) in [(pair[0], pair[1]), (pair[1], pair[0])] {
        match state(name) {
            FileState::Present => {}
            state @ (FileState::BrokenLink | FileState::NotAFile) => {
                problems.extend(state.unusable(format!("{folder}/{name}")))
            }
            FileState::Absent => problems.push(Problem::Missing(format!(
                "{folder}/{name} (beside {other}; or tokenizer.json instead of both)"
            ))),
        }
    }
    problems
}

fn prefix_problem(problem: Problem, folder: &str) -> Problem {
    match problem {
        Problem::Missing(p) => Problem::Missing(format!("{folder}/{p}")),
        Problem::BrokenLink(p) => Problem::BrokenLink(format!("{folder}/{p}")),
        Problem::PickleOnly(p) => Problem::PickleOnly(format!("{folder}/{p}")),
        Problem::Invalid { file, reason } => Problem::Invalid {
            file: format!("{folder}/{file}"),
            reason,
        },
    }
}

/// Reduces an error to its message without the path prefix (the caller names the file itself).
pub(crate) fn short_reason(err: &LoadError) -> String {
    match err {
        LoadError::BadFile { message, .. } => message.clone(),
        LoadError::Io { source, .. } => source.to_string(),
        LoadError::Candle { source, .. } => source.to_string(),
        other => other.to_string(),
    }
}

/// `[library, class]` per component name, as `model_index.json` declares them.
type DeclaredClasses = BTreeMap<String, (Option<String>, Option<String>)>;

fn parse_model_index(value: &serde_json::Value) -> (Option<String>, DeclaredClasses) {
    let mut entries = BTreeMap::new();
    let mut class = None;
    if let Some(obj) = value.as_object() {
        class = obj
            .get("_class_name")
            .and_then(|v| v.as_str())
            .map(str::to_owned);
        for (key, v) in obj {
            if key.starts_with('_') {
                continue;
            }
            if let Some([lib, cls]) = v.as_array().map(|a| a.as_slice()) {
                entries.insert(
                    key.clone(),
                    (
                        lib.as_str().map(str::to_owned),
                        cls.as_str().map(str::to_owned),
                    ),
                );
            }
        }
    }
    (class, entries)
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum FileState {
    Present,
    /// A symlink whose target is gone (a hub-cache blob deleted).
    BrokenLink,
    /// Something other than a file where a file should be (a folder, a named pipe).
    NotAFile,
    Absent,
}

impl FileState {
    /// The problem of an unusable file named `name` (`None` when present or absent).
    fn unusable(&self, name: String) -> Option<Problem> {
        match self {
            FileState::BrokenLink => Some(Problem::BrokenLink(name)),
            FileState::NotAFile => Some(Problem::Invalid {
                file: name,
                reason: "not a regular file (a folder?)".into(),
            }),
            FileState::Present | FileState::Absent => None,
        }
    }
}

fn file_state(path: &Path) -> FileState {
    if path.is_file() {
        FileState::Present
    } else if fs::metadata(path).is_ok() {
        FileState::NotAFile
    } else if fs::symlink_metadata(path).is_ok() {
        FileState::BrokenLink
    } else {
        FileState::Absent
    }
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Resolves a user-given model path: a hub-cache `models--org--name` folder becomes its snapshot.
pub fn resolve_model_path(path: &Path) -> Result<PathBuf, LoadError> {
    if !path.is_dir() {
        return Err(LoadError::NotFound(path.to_path_buf()));
    }
    // `models--org--name/snapshots` itself: resolve from its parent.
    if path.file_name().is_some_and(|n| n == "snapshots")
        && !path.join("model_index.json").exists()
        && path
            .parent()
            .is_some_and(|p| p.join("refs").is_dir() || p.join("blobs").is_dir())
    {
        if let Some(parent) = path.parent() {
            return resolve_model_path(parent);
        }
    }
    let snapshots = path.join("snapshots");
    // A folder that has the pipeline files itself is taken as is, even if it happens to hold `snapshots/`.
    if path.join("model_index.json").exists() || !snapshots.is_dir() {
        return Ok(path.to_path_buf());
    }
    let refs_main = path.join("refs").join("main");
    if let Ok(rev) = fs::read_to_string(&refs_main) {
        let candidate = snapshots.join(rev.trim());
        if !rev.trim().is_empty() && candidate.is_dir() {
            return Ok(candidate);
        }
    }
    let entries = fs::read_dir(&snapshots).map_err(|source| LoadError::Io {
        path: snapshots.clone(),
        source,
    })?;
    let mut newest: Option<(std::time::SystemTime, PathBuf)> = None;
    for entry in entries.flatten() {
        let p = entry.path();
        if !p.is_dir() {
            continue;
        }
        let modified = entry
            .metadata()
            .and_then(|m| m.modified())
            .unwrap_or(std::time::UNIX_EPOCH);
        // Ties broken by name so the choice does not depend on directory order.
        let better = match &newest {
            None => true,
            Some((t, q)) => modified > *t || (modified == *t && p > *q),
        };
        if better {
            newest = Some((modified, p));
        }
    }
    newest.map(|(_, p)| p).ok_or_else(|| LoadError::Incomplete {
        root: path.to_path_buf(),
        problems: vec![Problem::Missing("snapshots/<revision>/".into())],
    })
}

/// Errors from [`find_weight_files`] before they are folded into a folder-level report.
#[derive(Debug)]
enum WeightSearchError {
    Problems(Vec<Problem>),
    Other(LoadError),
}

impl WeightSearchError {
    fn into_load_error(self, dir: &Path) -> LoadError {
        match self {
            WeightSearchError::Problems(problems) => LoadError::Incomplete {
                root: dir.to_path_buf(),
                problems,
            },
            WeightSearchError::Other(e) => e,
        }
    }
}

/// Splits `name.fp16.safetensors` into (`name`, Some("fp16")); shard numbers stay in the stem.
fn split_variant(stem: &str) -> (&str, Option<&str>) {
    match stem.rsplit_once('.') {
        Some((base, variant))
            if !variant.is_empty() && variant.chars().all(|c| c.is_ascii_alphanumeric()) =>
        {
            (base, Some(variant))
        }
        _ => (stem, None),
    }
}

/// True for shard file stems like `model-00001-of-00002` (with or without a variant).
fn is_shard_stem(stem: &str) -> bool {
    let parts: Vec<&str> = stem.rsplitn(4, '-').collect();
    parts.len() == 4
        && parts[1] == "of"
        && !parts[0].is_empty()
        && parts[0].chars().all(|c| c.is_ascii_digit())
        && !parts[2].is_empty()
        && parts[2].chars().all(|c| c.is_ascii_digit())
}

/// Chooses the safetensors files of one component folder.
///
/// Preference: plain names over variants (`fp16` first among variants, then alphabetical); within the
/// chosen variant a sharded index wins, else every non-shard safetensors file is used (several files are
/// merged, which also serves folders that split encoder and decoder).
pub fn find_weight_files(dir: &Path) -> Result<WeightFiles, LoadError> {
    find_weight_files_inner(dir).map_err(|e| e.into_load_error(dir))
}

fn find_weight_files_inner(dir: &Path) -> Result<WeightFiles, WeightSearchError> {
    let entries = fs::read_dir(dir).map_err(|source| {
        if source.kind() == std::io::ErrorKind::NotFound {
            WeightSearchError::Problems(vec![Problem::Missing(format!("{}/", dir.display()))])
        } else {
            WeightSearchError::Other(LoadError::Io {
                path: dir.to_path_buf(),
                source,
            })
        }
    })?;
    // variant -> (index files, single files)
    let mut groups: BTreeMap<Option<String>, (Vec<PathBuf>, Vec<PathBuf>)> = BTreeMap::new();
    let mut pickles = Vec::new();
    let mut broken = Vec::new();
    let mut names: Vec<(String, PathBuf)> = entries
        .flatten()
        .map(|e| (e.file_name().to_string_lossy().into_owned(), e.path()))
        .collect();
    names.sort();
    for (name, path) in names {
        if name.starts_with('.') {
            continue;
        }
        let is_weight_like = name.ends_with(".safetensors")
            || name.ends_with(".safetensors.index.json")
            || [".bin", ".ckpt", ".pt", ".pth"]
                .iter()
                .any(|ext| name.ends_with(ext));
        if !is_weight_like {
            continue;
        }
        if let Some(problem) = file_state(&path).unusable(name.clone()) {
            broken.push(problem);
            continue;
        }
        if let Some(stem) = name.strip_suffix(".safetensors.index.json") {
            let (_, variant) = split_variant(stem);
            groups
                .entry(variant.map(str::to_owned))
                .or_default()
                .0
                .push(path);
        } else if let Some(stem) = name.strip_suffix(".safetensors") {
            if is_shard_stem(stem) {
                continue; // listed by its index
            }
            let (_, variant) = split_variant(stem);
            groups
                .entry(variant.map(str::to_owned))
                .or_default()
                .1
                .push(path);
        } else if !name.ends_with(".index.json") {
            pickles.push(name);
        }
    }
    if !broken.is_empty() {
        // Never fall back to another variant silently when part of a download is gone.
        return Err(WeightSearchError::Problems(broken));
    }
    let variant = if groups.contains_key(&None) {
        Some(None)
    } else if groups.contains_key(&Some("fp16".to_string())) {
        Some(Some("fp16".to_string()))
    } else {
        groups.keys().next().cloned()
    };
    let Some(variant) = variant else {
        if let Some(first) = pickles.into_iter().next() {
            return Err(WeightSearchError::Problems(vec![Problem::PickleOnly(
                first,
            )]));
        }
        let expected = if dir.file_name().is_some_and(|n| n == "text_encoder") {
            Component::TextEncoder.default_weight_file()
        } else {
            Component::Unet.default_weight_file()
        };
        return Err(WeightSearchError::Problems(vec![Problem::Missing(
            expected.to_string(),
        )]));
    };
    let (indexes, singles) = groups.remove(&variant).unwrap_or_default();
    if let Some(index_path) = indexes.first() {
        let index: ShardIndex = read_json(index_path).map_err(|e| {
            WeightSearchError::Problems(vec![Problem::Invalid {
                file: file_name(index_path),
                reason: short_reason(&e),
            }])
        })?;
        let shard_names: BTreeSet<&String> = index.weight_map.values().collect();
        let mut files = Vec::new();
        let mut problems = Vec::new();
        for shard in shard_names {
            let path = dir.join(shard);
            match file_state(&path) {
                FileState::Present => files.push(path),
                state @ (FileState::BrokenLink | FileState::NotAFile) => {
                    problems.extend(state.unusable(shard.clone()))
                }
                FileState::Absent => problems.push(Problem::Missing(shard.clone())),
            }
        }
        if files.is_empty() && problems.is_empty() {
            problems.push(Problem::Invalid {
                file: file_name(index_path),
                reason: "weight_map lists no files".into(),
            });
        }
        if !problems.is_empty() {
            return Err(WeightSearchError::Problems(problems));
        }
        return Ok(WeightFiles {
            files,
            variant,
            sharded: true,
        });
    }
    // The file diffusers/transformers write wins over stray extra files; otherwise all are merged.
    let standard = singles.iter().find(|p| {
        let name = file_name(p);
        let stem = name.strip_suffix(".safetensors").unwrap_or(&name);
        matches!(split_variant(stem).0, "diffusion_pytorch_model" | "model")
    });
    let files = match standard {
        Some(p) => vec![p.clone()],
        None => singles,
    };
    Ok(WeightFiles {
        files,
        variant,
        sharded: false,
    })
}

/// Reads and parses a JSON file, naming the file in any error.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, LoadError> {
    let text = fs::read_to_string(path).map_err(|source| LoadError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| LoadError::BadFile {
        path: path.to_path_buf(),
        message: format!("invalid JSON: {e}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_safetensors(path: &Path, tensors: &[(&str, &[usize])]) {
        let tensors: std::collections::HashMap<String, candle_core::Tensor> = tensors
            .iter()
            .map(|(name, shape)| {
                let t = candle_core::Tensor::zeros(*shape, DType::F32, &Device::Cpu).unwrap();
                (name.to_string(), t)
            })
            .collect();
        candle_core::safetensors::save(&tensors, path).unwrap();
    }

    #[test]
    fn variant_and_shard_names() {
        assert_eq!(
            split_variant("diffusion_pytorch_model.fp16"),
            ("diffusion_pytorch_model", Some("fp16"))
        );
        assert_eq!(split_variant("model"), ("model", None));
        assert!(is_shard_stem("model-00001-of-00002"));
        assert!(is_shard_stem("model.fp16-00001-of-00002"));
        assert!(!is_shard_stem("taesd-decoder"));
    }

    #[test]
    fn plain_file_preferred_over_fp16_variant() {
        let dir = tempfile::tempdir().unwrap();
        write_safetensors(
            &dir.path().join("diffusion_pytorch_model.safetensors"),
            &[("a", &[2])],
        );
        write_safetensors(
            &dir.path().join("diffusion_pytorch_model.fp16.safetensors"),
            &[("a", &[2])],
        );
        let w = find_weight_files(dir.path()).unwrap();
        assert_eq!(w.variant, None);
        assert_eq!(
            w.files,
            vec![dir.path().join("diffusion_pytorch_model.safetensors")]
        );
        fs::remove_file(dir.path().join("diffusion_pytorch_model.safetensors")).unwrap();
        let w = find_weight_files(dir.path()).unwrap();
        assert_eq!(w.variant.as_deref(), Some("fp16"));
    }

    #[test]
    fn standard_name_wins_over_extra_files_and_others_merge() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        write_safetensors(&d.join("taesd_encoder.safetensors"), &[("a", &[2])]);
        write_safetensors(&d.join("taesd_decoder.safetensors"), &[("b", &[2])]);
        assert_eq!(find_weight_files(d).unwrap().files.len(), 2);
        write_safetensors(
            &d.join("diffusion_pytorch_model.safetensors"),
            &[("c", &[2])],
        );
        assert_eq!(
            find_weight_files(d).unwrap().files,
            vec![d.join("diffusion_pytorch_model.safetensors")]
        );
    }

    #[test]
    fn sharded_index_lists_its_shards_and_reports_missing_ones() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        write_safetensors(&d.join("model-00001-of-00002.safetensors"), &[("a", &[2])]);
        write_safetensors(&d.join("model-00002-of-00002.safetensors"), &[("b", &[3])]);
        fs::write(
            d.join("model.safetensors.index.json"),
            r#"{"metadata":{},"weight_map":{"a":"model-00001-of-00002.safetensors","b":"model-00002-of-00002.safetensors"}}"#,
        )
        .unwrap();
        let w = find_weight_files(d).unwrap();
        assert!(w.sharded);
        assert_eq!(w.files.len(), 2);
        fs::remove_file(d.join("model-00002-of-00002.safetensors")).unwrap();
        let err = find_weight_files(d).unwrap_err().to_string();
        assert!(
            err.contains("missing model-00002-of-00002.safetensors"),
            "{err}"
        );
    }

    #[test]
    fn pickles_are_refused_with_advice() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("diffusion_pytorch_model.bin"), b"pickle").unwrap();
        let err = find_weight_files(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("diffusion_pytorch_model.bin is a PyTorch pickle"),
            "{err}"
        );
        assert!(err.contains("safetensors"), "{err}");
    }

    /// A folder where a weight file should be is named as such, not as a broken link; a dangling symlink
    /// is a broken link.
    #[test]
    fn a_folder_or_a_dangling_link_in_place_of_weights_is_named_for_what_it_is() {
        let dir = tempfile::tempdir().unwrap();
        fs::create_dir(dir.path().join("diffusion_pytorch_model.safetensors")).unwrap();
        let err = find_weight_files(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("diffusion_pytorch_model.safetensors: not a regular file")
                && !err.contains("broken link"),
            "{err}"
        );
        #[cfg(unix)]
        {
            let dir = tempfile::tempdir().unwrap();
            std::os::unix::fs::symlink(
                dir.path().join("gone"),
                dir.path().join("diffusion_pytorch_model.safetensors"),
            )
            .unwrap();
            let err = find_weight_files(dir.path()).unwrap_err().to_string();
            assert!(err.contains("broken link"), "{err}");
        }
    }

    #[test]
    fn hub_cache_folder_resolves_to_ref_or_newest_snapshot() {
        let dir = tempfile::tempdir().unwrap();
        let repo = dir.path().join("models--org--name");
        fs::create_dir_all(repo.join("snapshots/aaa")).unwrap();
        fs::create_dir_all(repo.join("snapshots/bbb")).unwrap();
        fs::create_dir_all(repo.join("refs")).unwrap();
        fs::write(repo.join("refs/main"), "aaa\n").unwrap();
        assert_eq!(
            resolve_model_path(&repo).unwrap(),
            repo.join("snapshots/aaa")
        );
        assert_eq!(
            resolve_model_path(&repo.join("snapshots")).unwrap(),
            repo.join("snapshots/aaa")
        );
        fs::remove_file(repo.join("refs/main")).unwrap();
        fs::remove_dir(repo.join("snapshots/aaa")).unwrap();
        assert_eq!(
            resolve_model_path(&repo).unwrap(),
            repo.join("snapshots/bbb")
        );
        assert!(matches!(
            resolve_model_path(&dir.path().join("nope")),
            Err(LoadError::NotFound(_))
        ));
    }

    #[test]
    fn incomplete_folder_lists_everything_in_one_error() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        fs::write(d.join("model_index.json"), "{}").unwrap();
        for sub in ["unet", "vae", "text_encoder", "tokenizer", "scheduler"] {
            fs::create_dir_all(d.join(sub)).unwrap();
        }
        fs::write(d.join("vae/config.json"), "{").unwrap();
        fs::write(d.join("tokenizer/vocab.json"), "{}").unwrap();
        let err = ModelDir::open(d).unwrap_err().to_string();
        assert!(!err.contains('\n'));
        for expected in [
            "missing unet/config.json, unet/diffusion_pytorch_model.safetensors",
            "text_encoder/model.safetensors",
            "tokenizer/merges.txt",
            "scheduler/scheduler_config.json",
            "vae/config.json: invalid JSON",
        ] {
            assert!(err.contains(expected), "{expected} not in {err}");
        }
        assert!(!err.contains("tokenizer/vocab.json"), "{err}");
        assert!(err.contains("or tokenizer.json instead"), "{err}");
        // Neither form: the one-file form is named too.
        fs::remove_file(d.join("tokenizer/vocab.json")).unwrap();
        let err = ModelDir::open(d).unwrap_err().to_string();
        assert!(
            err.contains("tokenizer/tokenizer.json (or vocab.json + merges.txt)"),
            "{err}"
        );
    }
}
