//! The vector–Jacobian product `rtc_vjp` needs, taken with Candle's autograd, for the velocity
//! networks of the Candle path (SmolVLA's expert, π0 and π0.5).
//!
//! In a step with `rtc_vjp` rows, those rows run their own forward pass with `x_t` a [`Var`],
//! and one `backward` of `<v(x_t), c>` gives `J_v(x_t)^T c` for the sampler's cotangent `c`. The
//! other rows run the untracked forward pass they run in any batch: they keep their bits (on
//! CUDA a tracked input takes `candle_ops`' compositions instead of the fused kernels), and the
//! backward pass spends nothing on them. Everything but `x_t` (prefix keys and values, masks,
//! RoPE tables, time embeddings, weights) is a constant of the graph. This holds for any network
//! whose velocity is per row, which is what lets one function serve both models.

use candle_core::{Device, Tensor, Var};
use kairos_engine_types::GuidanceMode;

use crate::EngineError;
use crate::guidance::RowGuide;

/// Where `rtc_vjp` is served, for the refusals of the paths that cannot serve it.
pub(crate) const VJP_PATH: &str = "the Candle path serves rtc_vjp (`--kernels candle`, or \
                                   `kernels = \"candle\"` in kairos.toml)";

/// The rows of a guided batch split by whether they need the backward pass.
pub(crate) struct VjpRows {
    vjp: Vec<usize>,
    plain: Vec<usize>,
}

impl VjpRows {
    /// The split of `guides`' rows, or `None` when no row is guided with `rtc_vjp`.
    pub(crate) fn new(guides: &[Option<RowGuide>]) -> Option<Self> {
        let (vjp, plain): (Vec<usize>, Vec<usize>) = (0..guides.len()).partition(|&r| {
            guides[r]
                .as_ref()
                .is_some_and(|g| g.mode == GuidanceMode::RtcVjp)
        });
        (!vjp.is_empty()).then_some(VjpRows { vjp, plain })
    }

    /// The rows guided with `rtc_vjp`, in batch order.
    pub(crate) fn vjp(&self) -> &[usize] {
        &self.vjp
    }

    /// The other rows, in batch order (possibly none).
    pub(crate) fn plain(&self) -> &[usize] {
        &self.plain
    }
}

/// `VelocityField::velocity_vjp` of a per-row velocity network over a batch split by `rows`:
/// `x`, `v` and `pullback` are `[row][chunk * width]`, each row a `[chunk, width]` sample.
/// `plain` (given when there are plain rows) is the untracked forward pass over the plain rows'
/// samples, `tracked` the forward pass over the `rtc_vjp` rows' (with their own context); each
/// returns `[rows, chunk, width]` velocities. The pullback is zero on the plain rows.
#[allow(clippy::too_many_arguments)]
pub(crate) fn velocity_vjp(
    rows: &VjpRows,
    (chunk, width): (usize, usize),
    device: &Device,
    x: &[f32],
    v: &mut [f32],
    cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    pullback: &mut [f32],
    plain: Option<impl FnOnce(&Tensor) -> Result<Tensor, EngineError>>,
    tracked: impl FnOnce(&Tensor) -> Result<Tensor, EngineError>,
) -> Result<(), EngineError> {
    let len = chunk * width;
    let gather = |x: &[f32], rows: &[usize]| -> Result<Tensor, EngineError> {
        let flat: Vec<f32> = rows
            .iter()
            .flat_map(|&r| x[r * len..(r + 1) * len].iter().copied())
            .collect();
        Ok(Tensor::from_vec(flat, (rows.len(), chunk, width), device)?)
    };
    if let Some(forward) = plain {
        let out = forward(&gather(x, rows.plain())?)?;
        scatter(&out.flatten_all()?.to_vec1::<f32>()?, rows.plain(), len, v);
    }
    let xt = Var::from_tensor(&gather(x, rows.vjp())?)?;
    let out = tracked(xt.as_tensor())?;
    scatter(&out.flatten_all()?.to_vec1::<f32>()?, rows.vjp(), len, v);
    // One backward pass of <v(x), c> gives J_v(x)^T c at x, for the vjp rows' cotangent.
    let c = gather(&cotangent(v), rows.vjp())?;
    let grads = (out * c)?.sum_all()?.backward()?;
    let g = grads.get(xt.as_tensor()).ok_or_else(|| {
        EngineError::InvalidInput("rtc_vjp: no gradient reached the sample".into())
    })?;
    pullback.fill(0.0);
    scatter(
        &g.flatten_all()?.to_vec1::<f32>()?,
        rows.vjp(),
        len,
        pullback,
    );
    Ok(())
}

/// Writes `values` (`[rows.len()][len]`) into rows `rows` of `out` (`[row][len]`).
fn scatter(values: &[f32], rows: &[usize], len: usize, out: &mut [f32]) {
    for (i, &r) in rows.iter().enumerate() {
        out[r * len..(r + 1) * len].copy_from_slice(&values[i * len..(i + 1) * len]);
    }
}
