//! `unet/config.json` of a diffusers `UNet2DConditionModel`, with diffusers' defaults for missing keys.

use serde::Deserialize;

/// A config value that diffusers accepts either as one value for all blocks or as a per-block list.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum PerBlock<T> {
    One(T),
    Many(Vec<T>),
}

impl<T: Clone> PerBlock<T> {
    /// The value for each of `blocks` blocks; `None` when a list has the wrong length.
    pub fn expand(&self, blocks: usize) -> Option<Vec<T>> {
        match self {
            PerBlock::One(v) => Some(vec![v.clone(); blocks]),
            PerBlock::Many(list) if list.len() == blocks => Some(list.clone()),
            PerBlock::Many(_) => None,
        }
    }
}

/// Mirrors diffusers' `UNet2DConditionModel` constructor arguments (SD 1.x subset plus the keys that must be
/// checked to reject architectures this implementation does not cover).
#[derive(Debug, Clone, Deserialize)]
pub struct UNetConfig {
    #[serde(default)]
    pub sample_size: Option<usize>,
    #[serde(default = "four")]
    pub in_channels: usize,
    #[serde(default = "four")]
    pub out_channels: usize,
    #[serde(default)]
    pub center_input_sample: bool,
    #[serde(default = "yes")]
    pub flip_sin_to_cos: bool,
    #[serde(default)]
    pub freq_shift: f64,
    #[serde(default = "default_down_blocks")]
    pub down_block_types: Vec<String>,
    #[serde(default = "default_mid_block")]
    pub mid_block_type: Option<String>,
    #[serde(default = "default_up_blocks")]
    pub up_block_types: Vec<String>,
    #[serde(default = "no_per_block")]
    pub only_cross_attention: PerBlock<bool>,
    #[serde(default = "default_channels")]
    pub block_out_channels: Vec<usize>,
    #[serde(default = "default_layers")]
    pub layers_per_block: PerBlock<usize>,
    #[serde(default = "one")]
    pub downsample_padding: usize,
    #[serde(default = "unit")]
    pub mid_block_scale_factor: f64,
    #[serde(default = "silu")]
    pub act_fn: String,
    #[serde(default = "default_groups")]
    pub norm_num_groups: Option<usize>,
    #[serde(default = "default_eps")]
    pub norm_eps: f64,
    #[serde(default = "default_cross_dim")]
    pub cross_attention_dim: PerBlock<usize>,
    #[serde(default = "default_transformer_layers")]
    pub transformer_layers_per_block: PerBlock<usize>,
    /// For SD 1.x configs (num_attention_heads null) this is really the number of heads (diffusers quirk).
    #[serde(default = "default_head_dim")]
    pub attention_head_dim: PerBlock<usize>,
    #[serde(default)]
    pub num_attention_heads: Option<PerBlock<usize>>,
    #[serde(default)]
    pub dual_cross_attention: bool,
    #[serde(default)]
    pub use_linear_projection: bool,
    #[serde(default)]
    pub class_embed_type: Option<String>,
    #[serde(default)]
    pub addition_embed_type: Option<String>,
    #[serde(default)]
    pub num_class_embeds: Option<usize>,
    /// Compute attention scores in f32; this implementation always does, so it only needs accepting.
    #[serde(default)]
    pub upcast_attention: bool,
    #[serde(default = "default_shift")]
    pub resnet_time_scale_shift: String,
    #[serde(default)]
    pub resnet_skip_time_act: bool,
    #[serde(default = "unit")]
    pub resnet_out_scale_factor: f64,
    #[serde(default = "positional")]
    pub time_embedding_type: String,
    #[serde(default)]
    pub time_embedding_dim: Option<usize>,
    #[serde(default)]
    pub time_embedding_act_fn: Option<String>,
    #[serde(default)]
    pub timestep_post_act: Option<String>,
    /// LCM: width of the guidance-scale embedding added to the time embedding through `cond_proj`.
    #[serde(default)]
    pub time_cond_proj_dim: Option<usize>,
    #[serde(default = "three")]
    pub conv_in_kernel: usize,
    #[serde(default = "three")]
    pub conv_out_kernel: usize,
    #[serde(default)]
    pub projection_class_embeddings_input_dim: Option<usize>,
    #[serde(default = "default_attention_type")]
    pub attention_type: String,
    #[serde(default)]
    pub class_embeddings_concat: bool,
    #[serde(default)]
    pub mid_block_only_cross_attention: Option<bool>,
    #[serde(default)]
    pub cross_attention_norm: Option<String>,
    #[serde(default)]
    pub encoder_hid_dim: Option<usize>,
    #[serde(default)]
    pub encoder_hid_dim_type: Option<String>,
    #[serde(default)]
    pub addition_time_embed_dim: Option<usize>,
    #[serde(default)]
    pub reverse_transformer_layers_per_block: Option<serde_json::Value>,
}

fn four() -> usize {
    4
}
fn three() -> usize {
    3
}
fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}
fn unit() -> f64 {
    1.0
}
fn silu() -> String {
    "silu".into()
}
fn positional() -> String {
    "positional".into()
}
fn default_attention_type() -> String {
    "default".into()
}
fn default_shift() -> String {
    "default".into()
}
fn default_down_blocks() -> Vec<String> {
    [
        "CrossAttnDownBlock2D",
        "CrossAttnDownBlock2D",
        "CrossAttnDownBlock2D",
        "DownBlock2D",
    ]
    .map(String::from)
    .to_vec()
}
fn default_up_blocks() -> Vec<String> {
    [
        "UpBlock2D",
        "CrossAttnUpBlock2D",
        "CrossAttnUpBlock2D",
        "CrossAttnUpBlock2D",
    ]
    .map(String::from)
    .to_vec()
}
fn default_mid_block() -> Option<String> {
    Some("UNetMidBlock2DCrossAttn".into())
}
fn no_per_block() -> PerBlock<bool> {
    PerBlock::One(false)
}
fn default_channels() -> Vec<usize> {
    vec![320, 640, 1280, 1280]
}
fn default_layers() -> PerBlock<usize> {
    PerBlock::One(2)
}
fn default_groups() -> Option<usize> {
    Some(32)
}
fn default_eps() -> f64 {
    1e-5
}
fn default_cross_dim() -> PerBlock<usize> {
    PerBlock::One(1280)
}
fn default_transformer_layers() -> PerBlock<usize> {
    PerBlock::One(1)
}
fn default_head_dim() -> PerBlock<usize> {
    PerBlock::One(8)
}

/// Kind of a down or up block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockKind {
    /// `CrossAttnDownBlock2D` / `CrossAttnUpBlock2D`
    CrossAttn,
    /// `DownBlock2D` / `UpBlock2D`
    Plain,
}

/// Per-block numbers resolved from the config (diffusers' quirks applied), in down-block order.
#[derive(Debug, Clone)]
pub struct ResolvedBlocks {
    pub down: Vec<BlockKind>,
    pub up: Vec<BlockKind>,
    pub heads: Vec<usize>,
    pub layers: Vec<usize>,
    pub transformer_layers: Vec<usize>,
    pub cross_attention_dim: Vec<usize>,
    pub only_cross_attention: Vec<bool>,
    pub groups: usize,
    pub time_embed_dim: usize,
    pub scale_shift: bool,
}

impl UNetConfig {
    /// Parses `config.json` text.
    pub fn from_json(text: &str) -> Result<Self, serde_json::Error> {
        serde_json::from_str(text)
    }

    /// SD 1.5's `unet/config.json` values (the struct defaults are diffusers' defaults, which differ).
    pub fn sd15() -> Self {
        let mut cfg: Self = serde_json::from_str("{}").expect("empty config parses with defaults");
        cfg.sample_size = Some(64);
        cfg.cross_attention_dim = PerBlock::One(768);
        cfg
    }

    /// Checks every option against what this implementation supports and resolves per-block values.
    /// The error lists all unsupported or inconsistent options at once.
    pub fn resolve(&self) -> Result<ResolvedBlocks, Vec<String>> {
        let mut problems = Vec::new();
        let n = self.block_out_channels.len();
        if n == 0 {
            problems.push("block_out_channels is empty".to_string());
        }
        let mut kinds = |types: &[String], names: [&str; 2], key: &str| -> Vec<BlockKind> {
            types
                .iter()
                .map(|t| {
                    if t == names[0] {
                        BlockKind::CrossAttn
                    } else if t == names[1] {
                        BlockKind::Plain
                    } else {
                        problems.push(format!(
                            "{key}: unsupported block type {t:?} (supported: {}, {})",
                            names[0], names[1]
                        ));
                        BlockKind::Plain
                    }
                })
                .collect()
        };
        let down = kinds(
            &self.down_block_types,
            ["CrossAttnDownBlock2D", "DownBlock2D"],
            "down_block_types",
        );
        let up = kinds(
            &self.up_block_types,
            ["CrossAttnUpBlock2D", "UpBlock2D"],
            "up_block_types",
        );
        if down.len() != n || up.len() != n {
            problems.push(format!(
                "down_block_types ({}) and up_block_types ({}) must both have one entry per block_out_channels ({n})",
                down.len(),
                up.len()
            ));
        }
        let mut reject = |ok: bool, text: String| {
            if !ok {
                problems.push(text);
            }
        };
        reject(
            self.mid_block_type.as_deref() == Some("UNetMidBlock2DCrossAttn"),
            format!(
                "mid_block_type = {:?} (supported: \"UNetMidBlock2DCrossAttn\")",
                self.mid_block_type
            ),
        );
        reject(
            matches!(self.act_fn.as_str(), "silu" | "swish"),
            format!("act_fn = {:?} (supported: \"silu\")", self.act_fn),
        );
        reject(
            self.class_embed_type.is_none(),
            format!(
                "class_embed_type = {:?} (supported: null)",
                self.class_embed_type
            ),
        );
        reject(
            self.num_class_embeds.is_none(),
            format!(
                "num_class_embeds = {:?} (supported: null)",
                self.num_class_embeds
            ),
        );
        reject(
            self.addition_embed_type.is_none(),
            format!(
                "addition_embed_type = {:?} (supported: null)",
                self.addition_embed_type
            ),
        );
        reject(
            self.encoder_hid_dim_type.is_none() && self.encoder_hid_dim.is_none(),
            "encoder_hid_dim / encoder_hid_dim_type set (supported: null)".to_string(),
        );
        reject(
            !self.dual_cross_attention,
            "dual_cross_attention = true (supported: false)".to_string(),
        );
        reject(
            self.time_embedding_type == "positional",
            format!(
                "time_embedding_type = {:?} (supported: \"positional\")",
                self.time_embedding_type
            ),
        );
        reject(
            self.time_embedding_act_fn.is_none(),
            format!(
                "time_embedding_act_fn = {:?} (supported: null)",
                self.time_embedding_act_fn
            ),
        );
        reject(
            self.timestep_post_act.is_none(),
            format!(
                "timestep_post_act = {:?} (supported: null)",
                self.timestep_post_act
            ),
        );
        reject(
            self.attention_type == "default",
            format!(
                "attention_type = {:?} (supported: \"default\")",
                self.attention_type
            ),
        );
        reject(
            self.cross_attention_norm.is_none(),
            format!(
                "cross_attention_norm = {:?} (supported: null)",
                self.cross_attention_norm
            ),
        );
        reject(
            !self.resnet_skip_time_act,
            "resnet_skip_time_act = true (supported: false)".to_string(),
        );
        reject(
            self.reverse_transformer_layers_per_block
                .as_ref()
                .is_none_or(|v| v.is_null()),
            "reverse_transformer_layers_per_block set (supported: null)".to_string(),
        );
        reject(
            matches!(
                self.resnet_time_scale_shift.as_str(),
                "default" | "scale_shift"
            ),
            format!(
                "resnet_time_scale_shift = {:?} (supported: \"default\", \"scale_shift\")",
                self.resnet_time_scale_shift
            ),
        );
        reject(
            self.conv_in_kernel % 2 == 1,
            format!("conv_in_kernel = {} (must be odd)", self.conv_in_kernel),
        );
        reject(
            self.conv_out_kernel % 2 == 1,
            format!("conv_out_kernel = {} (must be odd)", self.conv_out_kernel),
        );
        let groups = self.norm_num_groups.unwrap_or(0);
        reject(
            groups > 0,
            match self.norm_num_groups {
                None => "norm_num_groups = null (supported: a group count)".to_string(),
                Some(g) => format!("norm_num_groups = {g} (must be at least 1)"),
            },
        );

        let mut per_block = |name: &str, value: Option<Vec<usize>>| -> Vec<usize> {
            value.unwrap_or_else(|| {
                problems.push(format!(
                    "{name}: a list must have one entry per block ({n})"
                ));
                vec![1; n]
            })
        };
        // diffusers quirk: when num_attention_heads is null, attention_head_dim holds the head counts.
        let heads = per_block(
            "num_attention_heads / attention_head_dim",
            self.num_attention_heads
                .as_ref()
                .unwrap_or(&self.attention_head_dim)
                .expand(n),
        );
        let layers = per_block("layers_per_block", self.layers_per_block.expand(n));
        let transformer_layers = per_block(
            "transformer_layers_per_block",
            self.transformer_layers_per_block.expand(n),
        );
        let cross_attention_dim =
            per_block("cross_attention_dim", self.cross_attention_dim.expand(n));
        let only_cross_attention = self.only_cross_attention.expand(n).unwrap_or_else(|| {
            problems.push(format!(
                "only_cross_attention: a list must have one entry per block ({n})"
            ));
            vec![false; n]
        });
        for (i, (&c, &h)) in self.block_out_channels.iter().zip(&heads).enumerate() {
            if h == 0 || c % h != 0 {
                problems.push(format!(
                    "block {i}: {c} channels cannot be split into {h} attention heads"
                ));
            }
            if groups > 0 && c % groups != 0 {
                problems.push(format!(
                    "block {i}: {c} channels not divisible by norm_num_groups {groups}"
                ));
            }
        }
        if !problems.is_empty() {
            return Err(problems);
        }
        Ok(ResolvedBlocks {
            down,
            up,
            heads,
            layers,
            transformer_layers,
            cross_attention_dim,
            only_cross_attention,
            groups,
            time_embed_dim: self
                .time_embedding_dim
                .unwrap_or(self.block_out_channels[0] * 4),
            scale_shift: self.resnet_time_scale_shift == "scale_shift",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sd15_defaults_resolve_to_the_known_topology() {
        let cfg = UNetConfig::sd15();
        let r = cfg.resolve().unwrap();
        assert_eq!(r.heads, vec![8; 4]);
        assert_eq!(
            r.down,
            vec![
                BlockKind::CrossAttn,
                BlockKind::CrossAttn,
                BlockKind::CrossAttn,
                BlockKind::Plain
            ]
        );
        assert_eq!(r.time_embed_dim, 1280);
        assert_eq!(r.cross_attention_dim, vec![768; 4]);
    }

    #[test]
    fn unsupported_options_are_all_listed() {
        let cfg = UNetConfig::from_json(
            r#"{"class_embed_type": "timestep", "addition_embed_type": "text_time", "act_fn": "gelu",
                "attention_head_dim": [1, 2]}"#,
        )
        .unwrap();
        let problems = cfg.resolve().unwrap_err();
        let text = problems.join("\n");
        assert!(text.contains("class_embed_type"), "{text}");
        assert!(text.contains("addition_embed_type"), "{text}");
        assert!(text.contains("act_fn"), "{text}");
        assert!(text.contains("attention_head_dim"), "{text}");
    }

    #[test]
    fn per_block_head_list_is_used_as_head_counts() {
        let cfg = UNetConfig::from_json(
            r#"{"block_out_channels": [16, 32], "attention_head_dim": [2, 4], "norm_num_groups": 4,
                "down_block_types": ["CrossAttnDownBlock2D", "DownBlock2D"],
                "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D"]}"#,
        )
        .unwrap();
        assert_eq!(cfg.resolve().unwrap().heads, vec![2, 4]);
    }
}
