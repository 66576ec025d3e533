//! Tilings of the product library's plane routines: how many planes a cube runs, how deep each
//! shared-memory stage reaches along k, how many rows of tiles a plane owns, and whether a plane's
//! partition is double-buffered.
//!
//! The library infers one tiling per problem from the device's limits (`infer_blueprint_plane`); on an
//! H200 its tensor-core routines reached 5–15 TFLOP/s on SD 1.5's products where cuBLAS reaches 155
//! (`docs/gpu-results.md`), and no routine did much better, so the tiling is the next suspect. Here a
//! [`Tiling`] overrides the inference's options (the same function the library calls, so every field
//! the options do not name is the library's own choice) and the product runs on the resulting blueprint.
//! `vcedit bench matmul --tilings grid` times a grid of them (tools/gpu-check's `matmul-tilings`), and
//! `VCEDIT_GPU_MATMUL_TILING` runs every product of a process on one, so a whole UNet can be timed on the
//! best of the grid before it becomes a default.

use std::fmt;

use cubecl::client::Client;
use cubecl::prelude::TensorBinding;
use cubek_matmul::definition::{AvailableVectorSizes, MatmulElems, MatmulProblem};
use cubek_matmul::multi_level::components::stage::PartitionBuffering;
use cubek_matmul::multi_level::components::tile::TileMatmulKind;
use cubek_matmul::multi_level::definition::{BatchMatmulBlueprint, MultiRowStrategy};
use cubek_matmul::multi_level::routines::{infer_blueprint_plane, PlaneTilingBlueprintOptions};
use cubek_matmul::multi_level::Strategy as Routine;
use cubek_matmul::routine::BlueprintStrategy::Forced;
use cubek_std::InputBinding;

/// Options of the library's plane tiling; `None` leaves a choice to the library.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Tiling {
    /// Planes per cube (the library: as many as the cube's units allow, divided by a register factor).
    pub planes: Option<u32>,
    /// Instruction tiles per plane along k in one stage (the library: plane width / instruction k).
    pub k: Option<u32>,
    /// Rows of instruction tiles per plane (the library: 1).
    pub rows: Option<u32>,
    /// Double-buffered partitions (the library: single for the simple routines).
    pub double: Option<bool>,
}

impl Tiling {
    /// Parses `planes=8,k=4,rows=2,buffer=double` (any subset, any order) or `default`.
    pub fn parse(spec: &str) -> std::result::Result<Tiling, String> {
        let mut tiling = Tiling::default();
        let spec = spec.trim();
        if spec.is_empty() || spec == "default" {
            return Ok(tiling);
        }
        for part in spec.split(',') {
            let (key, value) = part
                .split_once('=')
                .map(|(k, v)| (k.trim(), v.trim()))
                .ok_or_else(|| format!("tiling '{spec}': '{part}' is not key=value"))?;
            let count = || match value.parse::<u32>() {
                Ok(v) if (1..=64).contains(&v) => Ok(Some(v)),
                _ => Err(format!(
                    "tiling '{spec}': {key} must be a count from 1 to 64, not '{value}'"
                )),
            };
            match key {
                "planes" => tiling.planes = count()?,
                "k" => tiling.k = count()?,
                "rows" => tiling.rows = count()?,
                "buffer" => {
                    tiling.double = match value {
                        "single" => Some(false),
                        "double" => Some(true),
                        _ => {
                            return Err(format!(
                                "tiling '{spec}': buffer must be single or double, not '{value}'"
                            ))
                        }
                    }
                }
                _ => {
                    return Err(format!(
                        "tiling '{spec}': unknown key '{key}' (expected planes, k, rows, buffer)"
                    ))
                }
            }
        }
        Ok(tiling)
    }

    /// The grid `vcedit bench matmul --tilings grid` times: the library's own choice first, then planes
    /// per cube × stage depth × rows per plane, each single- and double-buffered. (A cube's output is
    /// `planes` instruction tiles square: 2 planes, 32² outputs, is too little work for any card this is
    /// for, so the grid starts at 4.)
    pub fn grid() -> Vec<Tiling> {
        let mut grid = vec![Tiling::default()];
        for planes in [4, 8, 16] {
            for k in [1, 2, 4, 8] {
                for rows in [1, 2, 4] {
                    for double in [false, true] {
                        grid.push(Tiling {
                            planes: Some(planes),
                            k: Some(k),
                            rows: Some(rows),
                            double: Some(double),
                        });
                    }
                }
            }
        }
        grid
    }

    pub fn is_default(&self) -> bool {
        *self == Tiling::default()
    }
}

impl fmt::Display for Tiling {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts = Vec::new();
        if let Some(v) = self.planes {
            parts.push(format!("planes={v}"));
        }
        if let Some(v) = self.k {
            parts.push(format!("k={v}"));
        }
        if let Some(v) = self.rows {
            parts.push(format!("rows={v}"));
        }
        if let Some(v) = self.double {
            parts.push(format!("buffer={}", if v { "double" } else { "single" }));
        }
        if parts.is_empty() {
            f.write_str("default")
        } else {
            f.write_str(&parts.join(","))
        }
    }
}

/// The routines of [`super::TENSOR_CORE_ROUTINES`] a tiling applies to (the simple, single-stage family,
/// whose blueprint the plane inference makes), with their tile instruction.
fn tileable(routine: &str) -> Option<TileMatmulKind> {
    match routine {
        "simple_cyclic_cmma" | "simple_strided_cmma" | "simple_tilewise_cmma" => {
            Some(TileMatmulKind::Cmma)
        }
        "simple_cyclic_mma" => Some(TileMatmulKind::Mma),
        _ => None,
    }
}

/// `routine` forced onto a blueprint made with `tiling`'s options, for the product `lhs × rhs → out`;
/// `None` where the tiling does not apply to the routine or the inference declines it (the caller then
/// takes the routine's own blueprint).
pub(super) fn forced_routine(
    routine: &str,
    tiling: &Tiling,
    client: &Client,
    lhs: &InputBinding,
    rhs: &InputBinding,
    out: &TensorBinding,
    dtypes: &MatmulElems,
) -> Option<Routine> {
    let kind = tileable(routine)?;
    let blueprint = plane_blueprint(kind, tiling, client, lhs, rhs, out, dtypes)?;
    Some(match routine {
        "simple_strided_cmma" => Routine::SimpleStridedCmma(Forced(blueprint)),
        "simple_tilewise_cmma" => Routine::SimpleTilewiseCmma(Forced(blueprint)),
        "simple_cyclic_mma" => Routine::SimpleCyclicMma(Forced(blueprint)),
        _ => Routine::SimpleCyclicCmma(Forced(blueprint)),
    })
}

/// The library's plane inference for this problem with `tiling`'s options, as the simple routines call
/// it (single-buffered partitions, the tiny-problem selection, swizzling where the instruction wants it)
/// where the tiling names nothing.
pub(super) fn plane_blueprint(
    kind: TileMatmulKind,
    tiling: &Tiling,
    client: &Client,
    lhs: &InputBinding,
    rhs: &InputBinding,
    out: &TensorBinding,
    dtypes: &MatmulElems,
) -> Option<BatchMatmulBlueprint> {
    let address_type = lhs
        .required_address_type()
        .max(rhs.required_address_type())
        .max(out.required_address_type(dtypes.acc_global.size()));
    let problem = MatmulProblem::from_shapes_and_strides(
        lhs.shape().clone(),
        rhs.shape().clone(),
        out.shape.clone(),
        lhs.data().strides.clone(),
        rhs.data().strides.clone(),
        out.strides.clone(),
        dtypes.as_global_elems(),
        address_type,
        None,
        None,
    )
    .ok()?;
    let vector_sizes = AvailableVectorSizes::from_type_sizes(
        client,
        lhs.data_elem_size(),
        rhs.data_elem_size(),
        dtypes.acc_global.size(),
    )
    .filter_lhs_with_tensor(&problem.lhs_strides, &problem.lhs_shape, problem.lhs_layout)
    .filter_rhs_with_tensor(&problem.rhs_strides, &problem.rhs_shape, problem.rhs_layout)
    .filter_out_with_tensor(&problem.out_strides, &problem.out_shape)
    .pick_max()
    .ok()?;
    // As the library's device settings: a device that reports no plane width is taken as 32 wide.
    let plane_dim = match client.properties().hardware.plane_size_max {
        0 => 32,
        width => width,
    };
    let mut dtypes = dtypes.clone();
    if kind.can_cast_stage_element() {
        dtypes.adjust_stage_dtypes();
    }
    let options = PlaneTilingBlueprintOptions {
        partition_k: tiling.k,
        row_count: tiling.planes,
        multi_row_strategy: tiling
            .rows
            .map_or(MultiRowStrategy::Never, MultiRowStrategy::Always),
        partition_buffering: Some(match tiling.double {
            Some(true) => PartitionBuffering::Double,
            _ => PartitionBuffering::Single,
        }),
        tiny_selection_enabled: true,
        swizzled: kind.should_swizzle(client),
        ..Default::default()
    };
    infer_blueprint_plane(
        kind,
        client,
        &problem,
        plane_dim,
        dtypes,
        &vector_sizes,
        options,
    )
    .ok()
    .map(|(blueprint, _)| blueprint)
}

#[cfg(test)]
mod tests {
    use super::super::super::testing::{device_or_skip, relative_error};
    use super::super::super::GpuTensor;
    use super::*;
    use candle_core::{Device, Tensor};
    use cubecl::ir::{ElemType, FloatKind};
    use cubek_matmul::definition::MatmulGlobalElems;

    /// Tilings reach the blueprint: the library's inference, given a tiling's options, makes a stage of
    /// that many planes, k tiles and rows per plane, buffered as asked. Where the device has plane
    /// operations (hardware; lavapipe's WGSL path has none), the product forced onto each blueprint
    /// matches the CPU.
    #[test]
    fn tilings_shape_the_blueprint_and_keep_the_product() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let (m, k, n) = (96, 64, 80);
        let a = Tensor::randn(0f32, 1.0, (m, k), &Device::Cpu).unwrap();
        let b = Tensor::randn(0f32, 1.0, (k, n), &Device::Cpu).unwrap();
        let want = a.matmul(&b).unwrap();
        let (ga, gb) = (
            GpuTensor::upload(&dev, &a).unwrap(),
            GpuTensor::upload(&dev, &b).unwrap(),
        );
        let f32_type = ElemType::Float(FloatKind::F32);
        let lhs = || InputBinding::new(ga.binding(&[1, m, k], &[m * k, k, 1]), f32_type);
        let rhs = || InputBinding::new(gb.binding(&[1, k, n], &[k * n, n, 1]), f32_type);
        let dtypes = MatmulElems::from_globals(&MatmulGlobalElems {
            lhs: f32_type,
            rhs: f32_type,
            out: f32_type,
        });
        for spec in [
            "default",
            "planes=2,k=1",
            "planes=4,k=2,rows=2,buffer=double",
        ] {
            let tiling = Tiling::parse(spec).unwrap();
            let out = ga.empty_like_device(vec![m, n]);
            let dst = || out.binding(&[1, m, n], &[m * n, n, 1]);
            // The plane-vector instruction: a plane routine's instruction every device has.
            let blueprint = plane_blueprint(
                TileMatmulKind::PlaneVec,
                &tiling,
                ga.client(),
                &lhs(),
                &rhs(),
                &dst(),
                &dtypes,
            )
            .unwrap_or_else(|| panic!("{spec}: no blueprint"));
            let scheme = &blueprint.tiling_scheme;
            if let Some(planes) = tiling.planes {
                let rows = tiling.rows.unwrap_or(1);
                assert_eq!(scheme.partition_size.m(), rows, "{spec}");
                assert_eq!(scheme.stage_size.m() * rows, planes, "{spec}: planes");
                assert_eq!(scheme.partition_size.n(), planes, "{spec}");
                assert_eq!(scheme.partition_size.k(), tiling.k.unwrap(), "{spec}");
            }
            let double = blueprint.partition_buffering == PartitionBuffering::Double;
            assert_eq!(double, tiling.double == Some(true), "{spec}: buffering");
            let mut launch_dtypes = dtypes.clone();
            let launched = cubek_matmul::launch::launch_ref(
                &cubek_matmul::strategy::Strategy::MultiLevel(Routine::SimpleCyclicCmma(Forced(
                    blueprint,
                ))),
                ga.client(),
                lhs(),
                rhs(),
                dst(),
                &mut launch_dtypes,
            );
            match launched {
                Ok(()) => {
                    let rel = relative_error(&out.to_cpu().unwrap(), &want);
                    assert!(rel < 1e-5, "{spec}: relative error {rel:.2e}");
                }
                Err(e) => {
                    let e = format!("{e}");
                    assert!(e.contains("Plane-wide operations"), "{spec}: {e}");
                }
            }
        }
    }

    #[test]
    fn tilings_parse_print_and_refuse_what_is_wrong() {
        let t = Tiling::parse("planes=8, k=4,rows=2,buffer=double").unwrap();
        assert_eq!(
            t,
            Tiling {
                planes: Some(8),
                k: Some(4),
                rows: Some(2),
                double: Some(true)
            }
        );
        assert_eq!(t.to_string(), "planes=8,k=4,rows=2,buffer=double");
        assert_eq!(Tiling::parse(&t.to_string()).unwrap(), t);
        assert!(Tiling::parse("default").unwrap().is_default());
        assert_eq!(Tiling::parse("k=2").unwrap().to_string(), "k=2");
        for (bad, says) in [
            ("planes=0", "count from 1 to 64"),
            ("k=many", "count from 1 to 64"),
            ("buffer=triple", "single or double"),
            ("depth=2", "unknown key 'depth'"),
            ("planes", "not key=value"),
        ] {
            let e = Tiling::parse(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
        let grid = Tiling::grid();
        assert!(grid[0].is_default());
        assert_eq!(grid.len(), 1 + 3 * 4 * 3 * 2);
        let distinct: std::collections::HashSet<String> =
            grid.iter().map(|t| t.to_string()).collect();
        assert_eq!(distinct.len(), grid.len());
    }
}
