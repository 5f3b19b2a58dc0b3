//! The flow-matching sampler shared by every model: seeded noise, LeRobot's Euler schedule, and
//! the per-step updates `U`.
//!
//! LeRobot (`policies/common/flow_matching.py::euler_integrate`, from openpi) integrates the
//! learned velocity from `t = 1` (noise) to `t = 0` (actions): `dt = -1/K`, `t_k = 1 + k dt`
//! (computed in f64, passed to the model as f32), `x <- x + dt * v(x, t_k)` in f32. Kairos
//! records each `dt * v` as the update `U[k]`, so `noise + U[0] + .. + U[K-1]` is the chunk,
//! exactly, when summed in that order.

use kairos_engine_types::GuidanceMode;

use crate::guidance::RowGuide;
use crate::{ActionChunk, ActionRequest, EngineError};

/// LeRobot's Euler schedule with `steps` steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Schedule {
    /// Number of Euler steps `K`.
    pub steps: usize,
}

impl Schedule {
    /// The step `dt = -1/K` as the f32 factor the update multiplies by.
    pub fn dt(&self) -> f32 {
        (-1.0f64 / self.steps as f64) as f32
    }

    /// The time `t_k = 1 + k dt` at which step `k` evaluates the velocity.
    pub fn time(&self, k: usize) -> f32 {
        (1.0f64 + k as f64 * (-1.0f64 / self.steps as f64)) as f32
    }
}

/// Integrate `rows` independent samples, each `len` values, from `x` (the noise, overwritten by
/// the result). `velocity(k, t_k, x, v)` writes the velocity of all rows into `v`;
/// `updates` receives `U`, laid out `[row][k][len]`.
pub fn integrate(
    schedule: Schedule,
    rows: usize,
    len: usize,
    x: &mut [f32],
    updates: &mut [f32],
    velocity: impl FnMut(usize, f32, &[f32], &mut [f32]) -> Result<(), EngineError>,
) -> Result<(), EngineError> {
    let guides = vec![None; rows];
    let mut field = ClosureField(velocity);
    integrate_guided(schedule, rows, len, x, updates, &guides, None, &mut field)
}

/// A model's velocity field over a batch of rows.
pub trait VelocityField {
    /// Writes the velocity of every row at `x` and step `k` (time `t`) into `v`.
    fn velocity(&mut self, k: usize, t: f32, x: &[f32], v: &mut [f32]) -> Result<(), EngineError>;

    /// As [`VelocityField::velocity`], and then `pullback = J_v(x)^T c` for the cotangent
    /// `c = cotangent(v)` (all rows; zero on rows that need none): one backward pass through
    /// the network. Models without autograd keep this default, which refuses.
    fn velocity_vjp(
        &mut self,
        k: usize,
        t: f32,
        x: &[f32],
        v: &mut [f32],
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
        pullback: &mut [f32],
    ) -> Result<(), EngineError> {
        let _ = (k, t, x, v, cotangent, pullback);
        Err(EngineError::InvalidInput(
            "rtc_vjp needs a backward pass through the velocity network, which this model \
             path does not have"
                .into(),
        ))
    }
}

/// A closure as a [`VelocityField`] without a backward pass.
pub struct ClosureField<F>(pub F);

impl<F: FnMut(usize, f32, &[f32], &mut [f32]) -> Result<(), EngineError>> VelocityField
    for ClosureField<F>
{
    fn velocity(&mut self, k: usize, t: f32, x: &[f32], v: &mut [f32]) -> Result<(), EngineError> {
        (self.0)(k, t, x, v)
    }
}

/// [`integrate`] with a [`RowGuide`] per row (`None`: plain sampling): each guided row's
/// velocity is replaced by the guided one before its Euler update, and a hard prefix is written
/// after it ([`crate::guidance`]). Rows never read each other's guidance, so a row's result is
/// what it would be in a batch of its own (for a model whose velocity is per row).
/// `velocities`, when given (`[row][k][len]`), receives the velocity each step used: the
/// guided one on guided rows.
#[allow(clippy::too_many_arguments)]
pub fn integrate_guided(
    schedule: Schedule,
    rows: usize,
    len: usize,
    x: &mut [f32],
    updates: &mut [f32],
    guides: &[Option<RowGuide>],
    mut velocities: Option<&mut [f32]>,
    field: &mut dyn VelocityField,
) -> Result<(), EngineError> {
    let steps = schedule.steps;
    assert_eq!(x.len(), rows * len);
    assert_eq!(updates.len(), rows * steps * len);
    assert_eq!(guides.len(), rows);
    if let Some(v) = &velocities {
        assert_eq!(v.len(), rows * steps * len);
    }
    let dt = schedule.dt();
    let mut v = vec![0.0f32; rows * len];
    let vjp_rows: Vec<bool> = guides
        .iter()
        .map(|g| g.as_ref().is_some_and(|g| g.mode == GuidanceMode::RtcVjp))
        .collect();
    let any_vjp = vjp_rows.iter().any(|&b| b);
    let mut pullback = if any_vjp {
        vec![0.0f32; rows * len]
    } else {
        Vec::new()
    };
    let mut before = vec![0.0f32; len];
    for k in 0..steps {
        let t = schedule.time(k);
        // LeRobot passes `time` to the guidance as the f64 it computed (`1.0 + step * dt`).
        let time = 1.0f64 + k as f64 * (-1.0f64 / steps as f64);
        if any_vjp {
            let mut cotangent = |v: &[f32]| {
                let mut c = vec![0.0f32; rows * len];
                for r in (0..rows).filter(|&r| vjp_rows[r]) {
                    if let Some(g) = &guides[r] {
                        let span = r * len..(r + 1) * len;
                        let err = g.error(t, &x[span.clone()], &v[span.clone()]);
                        for (ci, e) in c[span].iter_mut().zip(err) {
                            *ci = t * e;
                        }
                    }
                }
                c
            };
            field.velocity_vjp(k, t, x, &mut v, &mut cotangent, &mut pullback)?;
        } else {
            field.velocity(k, t, x, &mut v)?;
        }
        let next_time = if k + 1 < steps {
            schedule.time(k + 1)
        } else {
            0.0
        };
        for r in 0..rows {
            let span = r * len..(r + 1) * len;
            let xr = &mut x[span.clone()];
            let vr = &mut v[span.clone()];
            if let Some(g) = &guides[r] {
                let p = vjp_rows[r].then(|| &pullback[span.clone()]);
                g.guide(time, t, xr, vr, p);
            }
            if let Some(out) = velocities.as_deref_mut() {
                out[(r * steps + k) * len..(r * steps + k + 1) * len].copy_from_slice(vr);
            }
            let ur = &mut updates[(r * steps + k) * len..(r * steps + k + 1) * len];
            if guides[r].is_some() {
                before.copy_from_slice(xr);
            }
            for ((xi, &vi), ui) in xr.iter_mut().zip(vr.iter()).zip(ur.iter_mut()) {
                *ui = dt * vi;
                *xi += *ui;
            }
            if let Some(g) = &guides[r] {
                g.after_step(next_time, &before, xr, ur);
            }
        }
    }
    Ok(())
}

/// One [`RowGuide`] per row of `layout` (rows are `[request][sample]`), from each request's
/// guidance: `None` for requests without it. `noise` is the rows' initial noise
/// (`[row][N][full_dim]`); `to_model` maps one robot action into the model's action space.
pub fn row_guides(
    requests: &[ActionRequest],
    layout: &RowLayout,
    noise: &[f32],
    to_model: &dyn Fn(&mut [f32]),
) -> Result<Vec<Option<RowGuide>>, EngineError> {
    let len = layout.chunk_len * layout.full_dim;
    let mut out = Vec::with_capacity(layout.rows());
    let mut row = 0;
    for (request, &samples) in requests.iter().zip(&layout.samples) {
        for _ in 0..samples {
            let guide = request
                .guidance
                .as_ref()
                .map(|g| {
                    RowGuide::prepare(
                        g,
                        layout.chunk_len,
                        layout.action_dim,
                        layout.full_dim,
                        noise.get(row * len..(row + 1) * len).unwrap_or(&[]),
                        to_model,
                    )
                })
                .transpose()?;
            out.push(guide);
            row += 1;
        }
    }
    Ok(out)
}

/// Standard-normal noise for sample `sample` of a request with `seed`: `len` values.
///
/// The generator is specified here, not borrowed from a crate whose stream may change between
/// versions: SplitMix64 seeded with `seed ^ (sample+1) * 0x9E3779B97F4A7C15`, two 53-bit
/// uniforms per pair of outputs, Box–Muller in f64, rounded to f32. The same (seed, sample)
/// gives the same noise in every batch and every Kairos version.
pub fn gaussian_noise(seed: u64, sample: usize, len: usize) -> Vec<f32> {
    let mut state = seed ^ (sample as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut next = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut out = Vec::with_capacity(len + 1);
    while out.len() < len {
        // u1 in (0, 1], u2 in [0, 1).
        let u1 = ((next() >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
        let u2 = (next() >> 11) as f64 / (1u64 << 53) as f64;
        let radius = (-2.0 * u1.ln()).sqrt();
        let angle = 2.0 * std::f64::consts::PI * u2;
        out.push((radius * angle.cos()) as f32);
        out.push((radius * angle.sin()) as f32);
    }
    out.truncate(len);
    out
}

/// Per-row results of a batched generation, cut into one [`ActionChunk`] per request.
///
/// Rows are `[request][sample]` in order; each row holds `chunk_len x full_dim` values of which
/// the first `action_dim` per action are the robot's (SmolVLA pads actions to 32).
pub struct RowLayout {
    /// Samples of each request, in order.
    pub samples: Vec<usize>,
    /// `K`.
    pub steps: usize,
    /// `N`.
    pub chunk_len: usize,
    /// Values per action in the model (padded).
    pub full_dim: usize,
    /// Values per action returned (`<= full_dim`).
    pub action_dim: usize,
}

impl RowLayout {
    /// Total rows.
    pub fn rows(&self) -> usize {
        self.samples.iter().sum()
    }

    /// Split row-major `noise`, `actions` (`[row][N][full]`) and `updates` (`[row][K][N][full]`)
    /// into chunks cut to `action_dim`.
    pub fn chunks(&self, noise: &[f32], actions: &[f32], updates: &[f32]) -> Vec<ActionChunk> {
        let (n, full, d, k) = (self.chunk_len, self.full_dim, self.action_dim, self.steps);
        let cut = |src: &[f32], out: &mut Vec<f32>| {
            for a in src.chunks_exact(full) {
                out.extend_from_slice(&a[..d]);
            }
        };
        let mut row = 0;
        self.samples
            .iter()
            .map(|&s| {
                let mut chunk = ActionChunk {
                    samples: s,
                    steps: k,
                    chunk_len: n,
                    action_dim: d,
                    actions: Vec::with_capacity(s * n * d),
                    updates: Vec::with_capacity(s * k * n * d),
                    noise: Vec::with_capacity(s * n * d),
                };
                for _ in 0..s {
                    cut(
                        &noise[row * n * full..(row + 1) * n * full],
                        &mut chunk.noise,
                    );
                    cut(
                        &actions[row * n * full..(row + 1) * n * full],
                        &mut chunk.actions,
                    );
                    cut(
                        &updates[row * k * n * full..(row + 1) * k * n * full],
                        &mut chunk.updates,
                    );
                    row += 1;
                }
                chunk
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lerobot_schedule() {
        let s = Schedule { steps: 10 };
        assert_eq!(s.dt(), -0.1f32);
        assert_eq!(s.time(0), 1.0);
        assert_eq!(s.time(3), 0.7f32);
        assert_eq!(s.time(9), (1.0f64 - 0.9f64) as f32);
    }

    #[test]
    fn noise_is_standard_normal_and_reproducible() {
        let a = gaussian_noise(7, 0, 100_001);
        assert_eq!(a, gaussian_noise(7, 0, 100_001));
        assert_ne!(a[..10], gaussian_noise(7, 1, 10)[..]);
        assert_ne!(a[..10], gaussian_noise(8, 0, 10)[..]);
        let mean = a.iter().map(|&v| f64::from(v)).sum::<f64>() / a.len() as f64;
        let var = a
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / a.len() as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.02,
            "mean {mean} var {var}"
        );
    }

    /// The test's per-row velocity field, `v = (r - x) t + 0.1` on row `r`, with its exact
    /// vector–Jacobian product `J^T c = -t c`.
    struct LinearField {
        rows: Vec<usize>,
        len: usize,
    }

    impl VelocityField for LinearField {
        fn velocity(
            &mut self,
            _k: usize,
            t: f32,
            x: &[f32],
            v: &mut [f32],
        ) -> Result<(), EngineError> {
            for (i, (vi, xi)) in v.iter_mut().zip(x).enumerate() {
                *vi = (self.rows[i / self.len] as f32 - xi) * t + 0.1;
            }
            Ok(())
        }

        fn velocity_vjp(
            &mut self,
            k: usize,
            t: f32,
            x: &[f32],
            v: &mut [f32],
            cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
            pullback: &mut [f32],
        ) -> Result<(), EngineError> {
            self.velocity(k, t, x, v)?;
            for (p, c) in pullback.iter_mut().zip(cotangent(v)) {
                *p = -t * c;
            }
            Ok(())
        }
    }

    /// Rows of one batch with different guidance (none, `rtc`, `inpaint`, `rtc_vjp`) each get
    /// exactly what they get alone: guidance reads and writes its own row only.
    #[test]
    fn a_mixed_batch_gives_each_row_what_it_gets_alone() {
        use kairos_engine_types::{Guidance, PrefixSchedule};
        let (rows, chunk, dim, steps) = (4, 4, 2, 5);
        let len = chunk * dim;
        let guidance = |mode| Guidance {
            mode,
            prefix: vec![0.5, -0.5, 0.25, 0.75, 1.0, 0.0],
            delay: 2,
            execution_horizon: 3,
            schedule: PrefixSchedule::Exp,
            max_guidance_weight: 5.0,
        };
        let noise: Vec<f32> = (0..rows)
            .flat_map(|r| gaussian_noise(r as u64, 0, len))
            .collect();
        let guide = |mode, r: usize| {
            RowGuide::prepare(
                &guidance(mode),
                chunk,
                dim,
                dim,
                &noise[r * len..(r + 1) * len],
                &|_| {},
            )
            .unwrap()
        };
        let guides = [
            None,
            Some(guide(GuidanceMode::Rtc, 1)),
            Some(guide(GuidanceMode::Inpaint, 2)),
            Some(guide(GuidanceMode::RtcVjp, 3)),
        ];
        // A per-row velocity field (as the models' are): row r pulls toward r - x.
        let field = |rows: Vec<usize>| LinearField { rows, len };
        let run = |which: Vec<usize>| {
            let mut x: Vec<f32> = which
                .iter()
                .flat_map(|&r| noise[r * len..(r + 1) * len].to_vec())
                .collect();
            let n = which.len();
            let mut u = vec![0.0; n * steps * len];
            let mut v = vec![0.0; n * steps * len];
            let g: Vec<Option<RowGuide>> = which.iter().map(|&r| guides[r].clone()).collect();
            integrate_guided(
                Schedule { steps },
                n,
                len,
                &mut x,
                &mut u,
                &g,
                Some(&mut v),
                &mut field(which.clone()),
            )
            .unwrap();
            (x, u, v)
        };
        let (x, u, v) = run((0..rows).collect());
        for r in 0..rows {
            let (xa, ua, va) = run(vec![r]);
            assert_eq!(&x[r * len..(r + 1) * len], &xa[..], "row {r}: actions");
            assert_eq!(
                &u[r * steps * len..(r + 1) * steps * len],
                &ua[..],
                "row {r}: updates"
            );
            assert_eq!(
                &v[r * steps * len..(r + 1) * steps * len],
                &va[..],
                "row {r}: velocities"
            );
        }
        // The guidance did something: the inpainted row ends on the committed actions, the rtc
        // row differs from the same row unguided.
        assert_eq!(&x[2 * len..2 * len + 4], &[0.5, -0.5, 0.25, 0.75]);
        let mut plain = noise[len..2 * len].to_vec();
        let mut pu = vec![0.0; steps * len];
        integrate_guided(
            Schedule { steps },
            1,
            len,
            &mut plain,
            &mut pu,
            &[None],
            None,
            &mut field(vec![1]),
        )
        .unwrap();
        assert_ne!(&x[len..2 * len], &plain[..]);
        // The rtc_vjp row differs from the same row with rtc: its pullback is not zero.
        let mut rtc = noise[3 * len..4 * len].to_vec();
        integrate_guided(
            Schedule { steps },
            1,
            len,
            &mut rtc,
            &mut pu,
            &[Some(RowGuide {
                mode: GuidanceMode::Rtc,
                ..guides[3].clone().unwrap()
            })],
            None,
            &mut field(vec![3]),
        )
        .unwrap();
        assert_ne!(&x[3 * len..4 * len], &rtc[..]);
    }

    #[test]
    fn updates_sum_to_the_result() {
        let noise = gaussian_noise(1, 0, 12);
        let mut x = noise.clone();
        let mut u = vec![0.0; 2 * 5 * 6];
        integrate(Schedule { steps: 5 }, 2, 6, &mut x, &mut u, |k, t, x, v| {
            for (vi, xi) in v.iter_mut().zip(x) {
                *vi = xi * t + k as f32;
            }
            Ok(())
        })
        .unwrap();
        for r in 0..2 {
            for i in 0..6 {
                let mut acc = noise[r * 6 + i];
                for k in 0..5 {
                    acc += u[(r * 5 + k) * 6 + i];
                }
                assert_eq!(acc, x[r * 6 + i]);
            }
        }
    }
}
