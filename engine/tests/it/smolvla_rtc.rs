//! Real-time chunking in the SmolVLA expert against LeRobot 0.6.1 with `rtc_config`
//! (`engine/tools/reference.py --rtc`, `golden/rtc.safetensors`): the `pair` observations, a
//! previous chunk of which the robot executed 2 actions, `d` in {0, 3, 7}, the linear and exp
//! prefix schedules; the guided velocity of every step and the chunk, on the fast kernels and on
//! the Candle path. Rows with different guidance share a batch bit for bit.

#![allow(clippy::unwrap_used)]

use crate::vjp_check;
use kairos_engine::guidance::RowGuide;
use kairos_engine::smolvla::{ExpertInput, SmolVlaPipeline};
use kairos_engine::weights::Checkpoint;
use kairos_engine::{
    ActionModel, ActionRequest, DeviceKind, EngineOptions, Guidance, GuidanceMode, Kernels,
    PrefixSchedule,
};

use crate::smolvla_goldens::{Goldens, fixture};
use crate::smolvla_processors::{max_abs_diff, observations};

/// `golden/rtc.safetensors` and `golden/rtc.json`.
struct RtcGoldens {
    ckpt: Checkpoint,
    meta: serde_json::Value,
}

impl RtcGoldens {
    fn open() -> Self {
        let dir = fixture().join("golden");
        let bytes = std::fs::read(dir.join("rtc.safetensors")).unwrap();
        let meta =
            serde_json::from_str(&std::fs::read_to_string(dir.join("rtc.json")).unwrap()).unwrap();
        RtcGoldens {
            ckpt: Checkpoint::from_bytes("rtc", bytes).unwrap(),
            meta,
        }
    }

    fn f32(&self, key: &str) -> Vec<f32> {
        let shape = self
            .ckpt
            .shape(key)
            .unwrap_or_else(|| panic!("no golden `{key}`"))
            .to_vec();
        self.ckpt.tensor(key, &shape).unwrap()
    }

    fn shape(&self, key: &str) -> Vec<usize> {
        self.ckpt.shape(key).unwrap().to_vec()
    }
}

fn options(kernels: Kernels) -> EngineOptions {
    EngineOptions {
        device: DeviceKind::Cpu,
        kernels,
        threads: 2,
        ..Default::default()
    }
}

fn schedule(name: &str) -> PrefixSchedule {
    match name {
        "linear" => PrefixSchedule::Linear,
        "exp" => PrefixSchedule::Exp,
        other => panic!("schedule {other}"),
    }
}

/// The guidance Kairos' server sends for the golden case: the previous chunk from the capture on
/// in the robot's units (LeRobot's `prev_chunk_left_over` after the postprocessor).
fn guidance(r: &RtcGoldens, row: usize, mode: GuidanceMode, sched: &str, d: usize) -> Guidance {
    let shape = r.shape("leftover");
    let per = shape[1] * shape[2];
    Guidance {
        mode,
        prefix: r.f32("leftover")[row * per..(row + 1) * per].to_vec(),
        delay: d,
        execution_horizon: r.meta["execution_horizon"].as_u64().unwrap() as usize,
        schedule: schedule(sched),
        max_guidance_weight: r.meta["max_guidance_weight"].as_f64().unwrap() as f32,
    }
}

/// Runs every golden case on the device and kernels of `options` and compares the guided
/// velocity of every step, the normalised chunk and the chunk in the robot's units.
fn rtc_matches_lerobot(options: EngineOptions) {
    let kernels = options.kernels;
    let device = options.device;
    let g = Goldens::open();
    let r = RtcGoldens::open();
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &options).unwrap();
    let expert = pipeline.expert();
    let d = expert.dims().clone();
    let observations = observations(&g, "pair");
    let prepared: Vec<_> = observations
        .iter()
        .map(|o| pipeline.checkpoint().prepare(o).unwrap())
        .collect();
    let prefixes = pipeline.prefixes(&prepared).unwrap();
    let batch = observations.len();
    let len = d.chunk * d.action_pad;
    let noise = r.f32("noise");
    assert_eq!(noise.len(), batch * len);
    let noises: Vec<Vec<Vec<f32>>> = (0..batch)
        .map(|b| vec![noise[b * len..(b + 1) * len].to_vec()])
        .collect();
    let inputs: Vec<ExpertInput<'_>> = prefixes
        .iter()
        .zip(&noises)
        .map(|(prefix, noise)| ExpertInput { prefix, noise })
        .collect();
    let unnormalizer = pipeline.checkpoint().postprocessor().unnormalizer.as_ref();
    let to_model = |a: &mut [f32]| {
        if let Some(n) = unnormalizer {
            n.normalize("action", a).unwrap();
        }
    };
    // The tolerance: LeRobot's own f32-vs-f64 error of the plain chunk, times the largest
    // guidance weight (the guidance multiplies the error of `x - t v` by up to it), with room
    // for the ten steps it compounds over.
    let bound = 10.0
        * r.meta["max_guidance_weight"].as_f64().unwrap() as f32
        * g.e_lr("pair.actions").max(16.0 * f32::EPSILON);
    let delays: Vec<usize> = r.meta["delays"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let mut cases: Vec<(GuidanceMode, &str, usize)> = ["linear", "exp"]
        .into_iter()
        .flat_map(|sched| delays.iter().map(move |&d| (GuidanceMode::Rtc, sched, d)))
        .collect();
    if kernels == Kernels::Candle {
        // The paper's guidance, with the true VJP (the Candle path's autograd).
        let case = &r.meta["vjp_case"];
        let sched = case["schedule"].as_str().unwrap();
        cases.push((
            GuidanceMode::RtcVjp,
            sched,
            case["delay"].as_u64().unwrap() as usize,
        ));
    }
    for (mode, sched, delay) in cases {
        {
            let key = format!("{}.{sched}.d{delay}", mode.as_str());
            let guides: Vec<Option<RowGuide>> = (0..batch)
                .map(|b| {
                    Some(
                        RowGuide::prepare(
                            &guidance(&r, b, mode, sched, delay),
                            d.chunk,
                            d.action_dim,
                            d.action_pad,
                            &noises[b][0],
                            &to_model,
                        )
                        .unwrap(),
                    )
                })
                .collect();
            // LeRobot's get_prefix_weights, exactly.
            assert_eq!(
                guides[0].as_ref().unwrap().weights,
                r.f32(&format!("{key}.weights")),
                "{key}.weights"
            );
            let out = expert.sample_guided(&inputs, &guides).unwrap();
            // Velocities: ours [row][step][N][pad], LeRobot's [step][row][N][pad].
            let want_v = r.f32(&format!("{key}.velocities"));
            let mut dv = 0.0f32;
            for (b, o) in out.iter().enumerate() {
                for k in 0..d.steps {
                    let ours = &o.velocities[k * len..(k + 1) * len];
                    let want = &want_v[(k * batch + b) * len..(k * batch + b + 1) * len];
                    dv = dv.max(max_abs_diff(ours, want));
                }
            }
            let ours_norm: Vec<f32> = out
                .iter()
                .flat_map(|o| {
                    o.actions
                        .chunks_exact(d.action_pad)
                        .flat_map(|a| a[..d.action_dim].to_vec())
                        .collect::<Vec<_>>()
                })
                .collect();
            let da = max_abs_diff(&ours_norm, &r.f32(&format!("{key}.actions_norm")));
            let ours: Vec<f32> = out
                .iter()
                .flat_map(|o| {
                    pipeline
                        .checkpoint()
                        .finish_actions(&o.actions, d.action_pad)
                        .unwrap()
                        .concat()
                })
                .collect();
            let du = max_abs_diff(&ours, &r.f32(&format!("{key}.actions")));
            eprintln!(
                "{device:?}/{kernels:?} {key}: velocities {dv:.3e}, actions_norm {da:.3e}, actions {du:.3e}, bound {bound:.3e}"
            );
            assert!(dv <= bound, "{key}: velocities differ by {dv:e}");
            assert!(da <= bound, "{key}: normalised actions differ by {da:e}");
            let scale = ours.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            assert!(du <= bound * scale, "{key}: actions differ by {du:e}");
        }
    }

    // Mixed batches: each row is what it is alone (row 0 guided with rtc, d = 3, and row 1
    // plain; on the Candle path also rtc_vjp beside a plain row and beside an rtc row).
    let row_guide = |mode, b: usize| {
        RowGuide::prepare(
            &guidance(&r, b, mode, "linear", 3),
            d.chunk,
            d.action_dim,
            d.action_pad,
            &noises[b][0],
            &to_model,
        )
        .unwrap()
    };
    let mut mixes = vec![[Some(GuidanceMode::Rtc), None]];
    if kernels != Kernels::Candle {
        // The fast kernels have no backward pass: an rtc_vjp row is refused, naming the path
        // that serves it.
        let refused = expert
            .sample_guided(&inputs, &[Some(row_guide(GuidanceMode::RtcVjp, 0)), None])
            .unwrap_err()
            .to_string();
        assert!(refused.contains("--kernels candle"), "{refused}");
    } else {
        mixes.push([Some(GuidanceMode::RtcVjp), None]);
        mixes.push([None, Some(GuidanceMode::RtcVjp)]);
        mixes.push([Some(GuidanceMode::Rtc), Some(GuidanceMode::RtcVjp)]);
    }
    for modes in mixes {
        let guides: Vec<Option<RowGuide>> = modes
            .iter()
            .enumerate()
            .map(|(b, m)| m.map(|m| row_guide(m, b)))
            .collect();
        let mixed = expert.sample_guided(&inputs, &guides).unwrap();
        for b in 0..batch {
            let alone = expert
                .sample_guided(&inputs[b..=b], &guides[b..=b])
                .unwrap()
                .remove(0);
            assert_eq!(mixed[b], alone, "{device:?}/{kernels:?} {modes:?}: row {b}");
            if guides[b].is_some() {
                assert_ne!(mixed[b], expert.sample(&inputs[b..=b]).unwrap()[0]);
            }
        }
    }
}

#[test]
fn rtc_on_the_fast_kernels_matches_lerobot() {
    rtc_matches_lerobot(options(Kernels::Auto));
}

#[test]
fn rtc_on_the_candle_path_matches_lerobot() {
    rtc_matches_lerobot(options(Kernels::Candle));
}

/// `rtc` and `rtc_vjp` on CUDA (Candle's fused kernels for the plain rows, the compositions for
/// the rows that track gradients), against the same goldens and bound, mixed batches included.
#[cfg(feature = "cuda")]
#[test]
fn rtc_on_cuda_matches_lerobot() {
    rtc_matches_lerobot(crate::smolvla_parity::cuda());
}

/// Served through the model interface: `rtc` and `inpaint` change the chunk (`inpaint` ends on
/// the committed actions) on both paths; `rtc_vjp` changes it differently from `rtc` on the
/// Candle path, is plain sampling where every prefix weight is zero, and is refused on the fast
/// kernels naming the path that serves it; the model says what it supports.
#[test]
fn the_served_model_applies_every_guidance_its_path_has() {
    let r = RtcGoldens::open();
    let g = Goldens::open();
    let obs = observations(&g, "pair").remove(0);
    for kernels in [Kernels::Auto, Kernels::Candle] {
        let model = SmolVlaPipeline::load(&fixture(), None, &options(kernels)).unwrap();
        let support = model.chunking().guidance;
        assert!(support.supports(GuidanceMode::Rtc) && support.supports(GuidanceMode::Inpaint));
        assert_eq!(
            support.supports(GuidanceMode::RtcVjp),
            kernels == Kernels::Candle
        );
        let request = |g: Option<Guidance>| ActionRequest {
            cameras: obs.images.keys().cloned().collect(),
            images: obs.images.values().cloned().collect(),
            state: obs.state.clone(),
            instruction: obs.task.clone(),
            samples: 1,
            seed: 5,
            guidance: g,
        };
        let plain = model.generate(&[request(None)]).unwrap().remove(0);
        let rtc = model
            .generate(&[request(Some(guidance(
                &r,
                0,
                GuidanceMode::Rtc,
                "linear",
                3,
            )))])
            .unwrap()
            .remove(0);
        assert_ne!(plain.actions, rtc.actions);
        let inpaint = guidance(&r, 0, GuidanceMode::Inpaint, "linear", 3);
        let chunk = model
            .generate(&[request(Some(inpaint.clone()))])
            .unwrap()
            .remove(0);
        // The hard prefix: the first d actions are the committed ones (through the model's
        // normalisation and back).
        let dim = chunk.action_dim;
        let got = &chunk.actions[..3 * dim];
        let want = &inpaint.prefix[..3 * dim];
        let scale = want.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        assert!(
            max_abs_diff(got, want) <= 1e-5 * scale,
            "{kernels:?}: {got:?} vs {want:?}"
        );
        let vjp = model.generate(&[request(Some(guidance(
            &r,
            0,
            GuidanceMode::RtcVjp,
            "linear",
            3,
        )))]);
        if kernels == Kernels::Candle {
            let vjp = vjp.unwrap().remove(0);
            assert_ne!(vjp.actions, plain.actions);
            assert_ne!(vjp.actions, rtc.actions);
            // `zeros` with no delay weighs every action 0: the error, its pullback and so the
            // correction are zero, and the chunk is plain sampling's, bit for bit.
            let unweighted = Guidance {
                schedule: PrefixSchedule::Zeros,
                delay: 0,
                ..guidance(&r, 0, GuidanceMode::RtcVjp, "linear", 0)
            };
            let chunk = model
                .generate(&[request(Some(unweighted))])
                .unwrap()
                .remove(0);
            assert_eq!(chunk, plain);
        } else {
            let refused = vjp.unwrap_err().to_string();
            assert!(
                refused.contains("rtc_vjp")
                    && refused.contains("backward")
                    && refused.contains("--kernels candle"),
                "{refused}"
            );
        }
    }
}

/// The pullback `rtc_vjp` takes from Candle's autograd is the transposed Jacobian of the
/// expert's velocity applied to the guidance error: its inner product with a direction `e`
/// agrees with a central difference of `<v(x), c>` along `e`.
///
/// The check and its bound: [`vjp_check`].
#[test]
fn the_candle_vjp_matches_a_finite_difference_of_the_velocity() {
    let r = RtcGoldens::open();
    let g = Goldens::open();
    let candle = SmolVlaPipeline::load(&fixture(), None, &options(Kernels::Candle)).unwrap();
    let fast = SmolVlaPipeline::load(&fixture(), None, &options(Kernels::Auto)).unwrap();
    let expert = candle.expert();
    let d = expert.dims().clone();
    let len = d.chunk * d.action_pad;
    let observations = observations(&g, "pair");
    let prepared = vec![candle.checkpoint().prepare(&observations[0]).unwrap()];
    let prefix = candle.prefixes(&prepared).unwrap().remove(0);
    let noise = r.f32("noise")[..len].to_vec();
    let unnormalizer = candle.checkpoint().postprocessor().unnormalizer.as_ref();
    let to_model = |a: &mut [f32]| {
        if let Some(n) = unnormalizer {
            n.normalize("action", a).unwrap();
        }
    };
    let guide = |mode| {
        RowGuide::prepare(
            &guidance(&r, 0, mode, "linear", 3),
            d.chunk,
            d.action_dim,
            d.action_pad,
            &noise,
            &to_model,
        )
        .unwrap()
    };
    let first_velocity =
        |expert: &kairos_engine::smolvla::SmolVlaExpert, x: &[f32], guide: Option<RowGuide>| {
            let noise = [x.to_vec()];
            let input = ExpertInput {
                prefix: &prefix,
                noise: &noise,
            };
            let guides: Vec<Option<RowGuide>> = guide.into_iter().map(Some).collect();
            expert.sample_guided(&[input], &guides).unwrap()[0].velocities[..len].to_vec()
        };
    let v_fast = first_velocity(fast.expert(), &noise, None);
    vjp_check::vjp_matches_a_finite_difference(
        "smolvla_tiny",
        &noise,
        |x, guide| first_velocity(expert, x, guide),
        guide,
        &v_fast,
        1e-2,
    );
}
