//! The fuzz targets' CI mode: every committed corpus input and every input that once crashed a
//! target (`tests/fuzz/corpus/<target>/`, `tests/fuzz/regressions/<target>/`) goes through the
//! same functions the afl.rs binary fuzzes (`kairos_server::fuzz_targets`). A target panics on a
//! broken invariant, so a regression fails this test. The seeds are built here from the real
//! message, trace and config types, so a protocol change that makes them stale fails too;
//! `KAIROS_FUZZ_BLESS=1 cargo test -p kairos-tests --test it fuzz_replay` rewrites them.
//! How to fuzz, and what the fuzzer found: `docs/RELIABILITY.md`, "6. Fuzzing".

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kairos_sdk::protocol::worker::{
    Chunks, Drain, Heartbeat, ProfilePointWire, ProfileWire, Refused, Register, Registered,
    RunBatch, WorkChunk, WorkRequest, WorkResult, WorkerMessage, WorkerTier,
};
use kairos_sdk::protocol::{
    DType, EndTask, ErrorCode, ErrorReply, FetchObservation, FreshObservation, Hello,
    HorizonSelection, Image, ImagePayload, IntervalUs, LastExecInfo, Limits, Message, ModelInfo,
    Observation, RemainingHint, Reply, RoundRecordWire, Submit, TaskEnded, TaskOutcome, Tensor,
    Timing, Welcome,
};
use kairos_sdk::trace::{
    HorizonSetting, RoundTrace, TaskTrace, TraceHeader, TraceSet, TraceSource,
};
use kairos_server::config::Config;
use kairos_server::fuzz_targets::{TARGETS, Target};
use kairos_server::openpi::msgpack::{Value, Writer};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

/// The files of `dir`, sorted; none if it does not exist (a target that never crashed has no
/// regressions directory).
fn inputs(dir: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut files: Vec<PathBuf> = entries
        .map(|e| e.expect("a readable directory entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
}

fn target(name: &str) -> Target {
    TARGETS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| *t)
        .unwrap_or_else(|| panic!("no fuzz target `{name}`"))
}

#[test]
fn every_committed_input_replays_through_its_target() {
    for (name, target) in TARGETS {
        let corpus = inputs(&fuzz_dir().join("corpus").join(name));
        assert!(!corpus.is_empty(), "tests/fuzz/corpus/{name} is empty");
        let mut accepted = 0;
        for file in &corpus {
            let data = std::fs::read(file).expect("a readable corpus file");
            accepted += usize::from(target(&data));
        }
        assert!(
            accepted > 0,
            "no input of tests/fuzz/corpus/{name} passes every check: the corpus no longer \
             reaches the end of the parser"
        );
        for file in inputs(&fuzz_dir().join("regressions").join(name)) {
            let data = std::fs::read(&file).expect("a readable regression file");
            // Each of these once panicked; the fixed code must take it without panicking
            // (accepting or refusing it, as the file's name says).
            target(&data);
        }
    }
}

#[test]
fn seeds_pass_their_target_and_are_committed() {
    let bless = std::env::var_os("KAIROS_FUZZ_BLESS").is_some();
    for (name, file, bytes) in seeds() {
        assert!(
            target(name)(&bytes),
            "seed {name}/{file} does not pass every check of its target"
        );
        let path = fuzz_dir().join("corpus").join(name).join(file);
        if bless {
            std::fs::create_dir_all(path.parent().expect("a corpus directory"))
                .expect("create the corpus directory");
            std::fs::write(&path, &bytes).expect("write a seed");
        } else {
            let committed = std::fs::read(&path).unwrap_or_default();
            assert!(
                committed == bytes,
                "{} is missing or stale; rerun with KAIROS_FUZZ_BLESS=1",
                path.display()
            );
        }
    }
}

/// `(target, file name, input)` for every seed.
fn seeds() -> Vec<(&'static str, &'static str, Vec<u8>)> {
    let mut seeds = Vec::new();
    for (file, message) in wire_messages() {
        let bytes = message.encode(u32::MAX).expect("a seed message encodes");
        seeds.push(("wire", file, bytes));
    }
    seeds.push(("trace", "two_rounds.jsonl", trace_file()));
    for (file, text) in configs() {
        seeds.push(("config", file, text.into_bytes()));
    }
    seeds.push((
        "plugin_params",
        "specs.txt",
        b"kairos:buckets=10,aging=4\nfifo\nthreshold:t=0.4,h_min=4\nstatic:h=8\nspread:threshold=0.1\n"
            .to_vec(),
    ));
    let mut png = vec![1];
    png.extend(encoded(image::ImageFormat::Png));
    seeds.push(("image", "rgb8x8.png", png));
    let mut jpeg = vec![0];
    jpeg.extend(encoded(image::ImageFormat::Jpeg));
    seeds.push(("image", "rgb8x8.jpg", jpeg));
    seeds.push(("openpi_msgpack", "libero.msgpack", openpi_libero()));
    seeds.push(("openpi_msgpack", "every_kind.msgpack", msgpack_every_kind()));
    seeds.push(("openpi_observation", "libero.msgpack", openpi_libero()));
    seeds.push(("openpi_observation", "aloha_chw.msgpack", openpi_aloha()));
    for (file, message) in worker_messages() {
        let bytes = message
            .encode(u32::MAX)
            .expect("a seed worker message encodes");
        seeds.push(("worker", file, bytes));
    }
    for (file, head) in [
        (
            "scrape.txt",
            "GET /metrics HTTP/1.1\r\nHost: kairos:9100\r\nUser-Agent: Prometheus/2.42.0\r\n\
             Accept: application/openmetrics-text;version=1.0.0\r\n\r\n",
        ),
        (
            "probe.txt",
            "GET /ready HTTP/1.1\r\nHost: 10.0.0.7:9100\r\nUser-Agent: kube-probe/1.32\r\n\r\n",
        ),
        ("head_page.txt", "HEAD / HTTP/1.0\r\n\r\n"),
        (
            "fleet.txt",
            "GET /api/fleet?t=1 HTTP/1.1\r\nHost: localhost\r\nAccept: */*\r\n\r\n",
        ),
    ] {
        seeds.push(("http", file, head.as_bytes().to_vec()));
    }
    seeds
}

/// A LIBERO-style openpi request as `openpi-client` sends it: an `f32` state of the fuzz
/// model's four values, an 8x8 RGB `uint8` image in `[H, W, C]`, a prompt.
fn openpi_libero() -> Vec<u8> {
    let mut w = Writer::new();
    w.map(3);
    w.str("observation/state")
        .ndarray_f32(&[4], &[0.1, -0.2, 0.3, 0.4]);
    let pixels: Vec<u8> = (0..8 * 8 * 3).map(|i| (i * 5 % 256) as u8).collect();
    w.str("observation/image")
        .ndarray_raw(&[8, 8, 3], "|u1", &pixels);
    w.str("prompt").str("pick up the black bowl");
    w.finish()
}

/// An ALOHA-style request: a channel-first `f32` image (transposed by the key map), a wrist
/// image in `uint16` (converted to `f32`), the state as two keys' worth in one `f64` array, a
/// numpy string scalar as the prompt.
fn openpi_aloha() -> Vec<u8> {
    let mut w = Writer::new();
    w.map(4);
    w.str("observation/state");
    let state: Vec<u8> = [0.5f64, -0.5, 0.25, 1.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    w.ndarray_raw(&[4], "<f8", &state);
    let chw: Vec<f32> = (0..3 * 4 * 5).map(|i| i as f32 / 60.0).collect();
    w.str("observation/image").ndarray_f32(&[3, 4, 5], &chw);
    let wrist: Vec<u8> = (0..4 * 4u16)
        .flat_map(|v| (v * 1000).to_le_bytes())
        .collect();
    w.str("observation/wrist_image")
        .ndarray_raw(&[4, 4, 1], "<u2", &wrist);
    w.str("prompt").map(3);
    w.bin(b"__npgeneric__").bool(true);
    w.bin(b"data").str("fold the towel");
    w.bin(b"dtype").str("<U14");
    w.finish()
}

/// One value of every msgpack kind the decoder reads.
fn msgpack_every_kind() -> Vec<u8> {
    let mut w = Writer::new();
    w.map(9);
    w.str("nil").value(&Value::Nil);
    w.str("bool").bool(false);
    w.str("uint").uint(1 << 40);
    w.str("int").int(-300);
    w.str("float").float(-0.125);
    w.str("bin").bin(&[0, 1, 2, 255]);
    w.str("ext").ext(5, &[1, 2, 3]);
    w.str("nested").array(2);
    w.array(1).map(1);
    w.str("deep").str(&"x".repeat(40));
    w.uint(7);
    w.str("scalar").map(3);
    w.bin(b"__npgeneric__").bool(true);
    w.bin(b"data").float(2.5);
    w.bin(b"dtype").str("<f8");
    w.finish()
}

/// One worker-protocol message of every kind, shaped for the fuzz targets' model (state of 4,
/// chunks of 16 actions of 4, 4 steps).
fn worker_messages() -> Vec<(&'static str, WorkerMessage)> {
    let model = ModelInfo {
        name: "fuzz".into(),
        chunk_len: 16,
        action_dim: 4,
        state_dim: 4,
        steps: 4,
        max_images: 2,
        cameras: Vec::new(),
    };
    let f32s = |shape: Vec<u32>| {
        let len: u32 = shape.iter().product();
        let values: Vec<f32> = (0..len).map(|i| i as f32 / 100.0).collect();
        Tensor::from_f32(shape, &values).expect("a tensor")
    };
    vec![
        (
            "register.bin",
            WorkerMessage::Register(Register {
                protocol: 1,
                token: "kairos_worker_0123456789abcdef".into(),
                worker_id: "gpu-0".into(),
                model,
                profile: ProfileWire {
                    model: "fuzz".into(),
                    device: "cuda:0".into(),
                    points: vec![
                        ProfilePointWire {
                            batch: 1,
                            latency_ms: 30.0,
                        },
                        ProfilePointWire {
                            batch: 4,
                            latency_ms: 60.0,
                        },
                    ],
                    max_batch: 4,
                },
                max_batch: 4,
                tier: WorkerTier::Auto,
            }),
        ),
        (
            "registered.bin",
            WorkerMessage::Registered(Registered {
                protocol: 1,
                engine: "worker-gpu-0".into(),
                heartbeat_ms: 500,
            }),
        ),
        (
            "refused.bin",
            WorkerMessage::Refused(Refused {
                reason: "the worker serves another model".into(),
                retryable: false,
            }),
        ),
        (
            "heartbeat.bin",
            WorkerMessage::Heartbeat(Heartbeat {
                load: 1,
                batches: 12,
            }),
        ),
        (
            "drain.bin",
            WorkerMessage::Drain(Drain {
                reason: "SIGTERM".into(),
            }),
        ),
        (
            "run_batch.bin",
            WorkerMessage::RunBatch(RunBatch {
                batch_id: 9,
                attempt: 0,
                deadline_ms: 2_000,
                requests: vec![WorkRequest {
                    state: f32s(vec![4]),
                    images: vec![Image {
                        camera: "cam0".into(),
                        payload: ImagePayload::Raw {
                            tensor: Tensor {
                                dtype: DType::U8,
                                shape: vec![4, 4, 3],
                                data: (0..48).collect(),
                            },
                        },
                    }],
                    instruction: "pick".into(),
                    samples: 1,
                    seed: 42,
                    guidance: None,
                }],
            }),
        ),
        (
            "chunks.bin",
            WorkerMessage::Chunks(Chunks {
                batch_id: 9,
                attempt: 0,
                compute_us: 25_000,
                results: vec![
                    WorkResult {
                        chunk: Some(WorkChunk {
                            actions: f32s(vec![1, 16, 4]),
                            updates: f32s(vec![1, 4, 16, 4]),
                            noise: f32s(vec![1, 16, 4]),
                        }),
                        error: None,
                    },
                    WorkResult {
                        chunk: None,
                        error: Some("state[1] is not finite".into()),
                    },
                ],
            }),
        ),
    ]
}

/// An 8x8 RGB gradient as a file.
fn encoded(format: image::ImageFormat) -> Vec<u8> {
    let img = image::RgbImage::from_fn(8, 8, |x, y| {
        image::Rgb([(x * 32) as u8, (y * 32) as u8, 128])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, format)
        .expect("an 8x8 image encodes");
    out.into_inner()
}

fn observation(images: Vec<ImagePayload>) -> Observation {
    Observation {
        captured_at_us: 990_000,
        state: Tensor::from_f32(vec![4], &[0.1, -0.2, 0.3, 0.4]).expect("a state tensor"),
        images: images
            .into_iter()
            .enumerate()
            .map(|(i, payload)| Image {
                camera: format!("cam{i}"),
                payload,
            })
            .collect(),
        instruction: "pick up the cube".into(),
    }
}

fn last_exec() -> LastExecInfo {
    LastExecInfo {
        exec_started_at_us: 900_000,
        actions_remaining: 4,
        control_hz: 50.0,
        round: None,
        delay: None,
    }
}

fn submit(images: Vec<ImagePayload>) -> Submit {
    Submit {
        task: 7,
        round: 3,
        sent_at_us: 1_000_000,
        observation: observation(images),
        last_exec: Some(last_exec()),
        horizon: Some(HorizonSelection {
            policy: "threshold".into(),
            params: BTreeMap::from([("t".to_string(), 0.4), ("h_min".to_string(), 2.0)]),
            samples: 1,
        }),
        remaining: Some(RemainingHint {
            rounds: Some(10),
            seconds: Some(4.5),
        }),
        attempt: 0,
        control_hz: Some(50.0),
        seed: None,
        chunking: None,
    }
}

/// One message of every kind, and `Submit` with every image payload.
fn wire_messages() -> Vec<(&'static str, Message)> {
    let raw_u8 = ImagePayload::Raw {
        tensor: Tensor {
            dtype: DType::U8,
            shape: vec![4, 4, 3],
            data: (0..48).collect(),
        },
    };
    let raw_f32 = ImagePayload::Raw {
        tensor: Tensor::from_f32(vec![2, 2, 1], &[0.0, 0.25, 0.5, 1.0]).expect("a raw image"),
    };
    let png = ImagePayload::Png {
        data: encoded(image::ImageFormat::Png),
    };
    let jpeg = ImagePayload::Jpeg {
        data: encoded(image::ImageFormat::Jpeg),
    };
    let limits = Limits::default();
    vec![
        (
            "hello.bin",
            Message::Hello(Hello {
                protocol: 1,
                token: "0123456789abcdef".into(),
                client: "fuzz-seed".into(),
            }),
        ),
        (
            "welcome.bin",
            Message::Welcome(Welcome {
                protocol: 1,
                server: "kairos".into(),
                robot: "default".into(),
                model: ModelInfo {
                    name: "flow-head".into(),
                    chunk_len: 16,
                    action_dim: 4,
                    state_dim: 4,
                    steps: 4,
                    max_images: 2,
                    cameras: Vec::new(),
                },
                limits,
            }),
        ),
        ("submit.bin", Message::Submit(submit(Vec::new()))),
        (
            "submit_raw.bin",
            Message::Submit(submit(vec![raw_u8, raw_f32])),
        ),
        ("submit_png.bin", Message::Submit(submit(vec![png]))),
        (
            "submit_jpeg.bin",
            Message::Submit(submit(vec![jpeg.clone()])),
        ),
        (
            "fetch.bin",
            Message::FetchObservation(FetchObservation {
                task: 7,
                round: 3,
                age_us: 40_000,
            }),
        ),
        (
            "fresh.bin",
            Message::FreshObservation(FreshObservation {
                sent_at_us: 1_000_000,
                observation: observation(vec![jpeg]),
            }),
        ),
        (
            "reply.bin",
            Message::Reply(Reply {
                task: 7,
                round: 3,
                horizon: 8,
                chunk_len: 16,
                actions: Tensor::from_f32(vec![8, 4], &[0.5; 32]).expect("actions"),
                policy: "threshold".into(),
                timing: Timing {
                    queue_us: 100,
                    refetch_us: 0,
                    inference_us: 2_000,
                    total_us: 2_100,
                    batch_size: 1,
                },
                start: None,
                delay: None,
                chunking: None,
            }),
        ),
        (
            "end_task.bin",
            Message::EndTask(EndTask {
                task: 7,
                outcome: TaskOutcome::Done,
                sent_at_us: 1_000_000,
                last_exec: Some(last_exec()),
            }),
        ),
        (
            "task_ended.bin",
            Message::TaskEnded(TaskEnded {
                task: 7,
                rounds: 1,
                wait_us: 300,
                attained_service_us: 2_000,
                history: vec![RoundRecordWire {
                    round: 0,
                    generation: Some(IntervalUs {
                        start_us: 1_000,
                        end_us: 3_000,
                    }),
                    execution: Some(IntervalUs {
                        start_us: 3_500,
                        end_us: 163_500,
                    }),
                    horizon: Some(8),
                }],
            }),
        ),
        (
            "error.bin",
            Message::Error(ErrorReply::new(
                ErrorCode::InvalidObservation,
                "state[2] is NaN",
            )),
        ),
    ]
}

fn trace_file() -> Vec<u8> {
    let round = |issued_at_action, horizon| RoundTrace {
        issued_at_action,
        aligned_at_action: None,
        horizon,
        executed: horizon,
        gen_latency_us: 30_000,
        round_trip_us: Some(31_000),
        obs_bytes: 2_048,
        confidence: Some(vec![0.5, 0.75, 1.0, 2.5]),
    };
    let set = TraceSet {
        header: TraceHeader::new(TraceSource::Recorded),
        tasks: vec![TaskTrace {
            task: 1,
            label: Some("libero/pick".into()),
            setting: "dynamic".into(),
            horizon: HorizonSetting {
                policy: "threshold".into(),
                params: BTreeMap::from([("t".to_string(), 0.4)]),
            },
            control_hz: 10.0,
            chunk_len: 4,
            total_actions: 7,
            rounds: vec![round(0, 4), round(3, 4)],
        }],
    };
    set.write(Vec::new()).expect("a trace set writes")
}

fn configs() -> Vec<(&'static str, String)> {
    let defaults = toml::to_string(&Config::default()).expect("the default config serialises");
    let full = r#"listen = "127.0.0.1:4433"
data_dir = "kairos-data"

[[robot]]
name = "arm-1"
token_sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"

[[engine]]
model = "builtin"
instances = 2

[[engine]]
model = "builtin"
tier = "cloud"
rtt_ms = 5.0

[scheduler]
policy = "kairos:buckets=10,aging=4"
stale_after_ms = 20
task_idle_timeout_s = 60

[horizon]
policy = "threshold"

[limits]
max_images = 2
max_image_pixels = 1048576

[connections]
max_connections = 64
hello_timeout_ms = 2000

[[plugin]]
file = "plugins/hloop.wasm"
name = "hloop"
fallback = "threshold"
deadline_ms = 5
"#;
    vec![("defaults.toml", defaults), ("full.toml", full.to_string())]
}
