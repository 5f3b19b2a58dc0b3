//! Fuzz targets: every parser that reads bytes a stranger controls, as a function of those bytes.
//!
//! Each target runs the real server code on `data` and panics only when an invariant breaks
//! (a parser panics, or a round trip disagrees with itself); an input that is merely invalid
//! returns `false`, one that passes every check returns `true` (the replay test uses that to
//! show that the seeds reach the deep end of each parser). Two callers share these functions,
//! so what the fuzzer explores is what CI replays:
//! - the coverage-guided fuzzer, `tests/fuzz/` (a crate outside the workspace, built with
//!   `cargo afl`; `scripts/fuzz.sh` runs it);
//! - the corpus replay test (`tests/tests/it/fuzz_replay.rs`), which feeds every committed seed
//!   and every input that once crashed (`tests/fuzz/corpus/`, `tests/fuzz/regressions/`) through
//!   the same targets on every `cargo test`.
//!
//! Results and how to run them: `docs/RELIABILITY.md`, "6. Fuzzing".

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;
use std::time::Duration;

use kairos_engine::image_features::pooled_features;
use kairos_engine::{ActionRequest, ImageInput, ModelSpec};
use kairos_sdk::protocol::worker::{WORKER_MAX_FRAME, WorkerMessage};
use kairos_sdk::protocol::{
    HorizonSelection, Image, ImagePayload, Limits, Message, Observation, Submit, Tensor, Validate,
    check_raw_image,
};
use kairos_sdk::trace::TraceSet;

use crate::config::{Config, OpenpiConfig, WorkersConfig};
use crate::openpi::{self, msgpack, observation};
use crate::plugin::factory::spec_params;
use crate::pool::check_output;
use crate::validation::{Validator, decode_images};
use crate::worker::wire::{chunk_from_wire, model_spec, profile_from_wire, request_from_wire};
use kairos_core::action::ActionManager;
use kairos_core::clock_map::ClockMap;
use kairos_core::horizon::{self, PolicyParams};
use kairos_core::registry::native_horizon_policies;
use kairos_core::scheduler::{PolicySpec, RobotId, build_policy};
use kairos_core::time::Timestamp;

/// A fuzz target: one input, panics only on a broken invariant; `true` if every check passed.
pub type Target = fn(&[u8]) -> bool;

/// Every target by name; the names are the directories of `tests/fuzz/corpus/` and the afl
/// binaries of `tests/fuzz/`.
pub const TARGETS: &[(&str, Target)] = &[
    ("wire", wire),
    ("trace", trace),
    ("config", config),
    ("plugin_params", plugin_params),
    ("image", image),
    ("openpi_msgpack", openpi_msgpack),
    ("openpi_observation", openpi_observation),
    ("worker", worker),
    ("http", http),
];

/// The served model's shape the targets validate against: the built-in flow head's state and a
/// camera budget of two, so that image and state checks are reachable.
fn validator() -> &'static Validator {
    static VALIDATOR: OnceLock<Validator> = OnceLock::new();
    VALIDATOR.get_or_init(|| Validator {
        spec: ModelSpec {
            cameras: Vec::new(),
            camera_aliases: Default::default(),
            name: "fuzz".into(),
            chunk_len: 16,
            action_dim: 4,
            state_dim: 4,
            steps: 4,
            max_images: 2,
        },
        limits: Limits::default(),
        chunking: Default::default(),
    })
}

/// The native horizon policies with the server's default (`threshold`).
fn actions() -> &'static ActionManager {
    static ACTIONS: OnceLock<ActionManager> = OnceLock::new();
    ACTIONS.get_or_init(|| {
        let natives = native_horizon_policies();
        match ActionManager::new(natives.clone(), &natives, "threshold", BTreeMap::new()) {
            Ok(actions) => actions,
            Err(e) => panic!("the native horizon policies do not build: {e}"),
        }
    })
}

/// A request read at server time 2^40 µs over a 100 µs round trip.
fn clock(sent_at_us: u64) -> ClockMap {
    ClockMap::new(
        Timestamp::from_micros(1 << 40),
        sent_at_us,
        Duration::from_micros(100),
    )
}

/// The wire decoder plus validation, every message kind: `data` is a frame stream as a robot
/// sends it. The first frame is decoded with the server's limits; a decoded message must
/// re-encode to bytes that decode to the same encoding; then it goes through the server's
/// checks for its kind (`Hello`, `Submit` with its images decoded, `FreshObservation`,
/// `EndTask`; the protocol's own checks for the server-to-robot kinds).
pub fn wire(data: &[u8]) -> bool {
    let validator = validator();
    let limits = &validator.limits;
    let Ok((message, used)) = Message::decode_from(data, limits.max_frame) else {
        return false;
    };
    assert!(
        used <= data.len(),
        "the decoder used bytes it was not given"
    );
    let encoded = message
        .encode(u32::MAX)
        .unwrap_or_else(|e| panic!("a decoded {} does not encode: {e}", message.kind()));
    let (again, again_used) = Message::decode_from(&encoded, u32::MAX)
        .unwrap_or_else(|e| panic!("a re-encoded {} does not decode: {e}", message.kind()));
    assert_eq!(
        again_used,
        encoded.len(),
        "a re-encoded frame has trailing bytes"
    );
    let reencoded = again.encode(u32::MAX).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        reencoded == encoded,
        "encoding is not stable across a round trip"
    );

    let protocol_ok = message.validate(limits).is_ok();
    match message {
        Message::Hello(hello) => validator.hello(&hello).is_ok(),
        Message::Submit(submit) => {
            let sent_at = submit.sent_at_us;
            let Ok(valid) = validator.submit(submit, RobotId(1), actions(), clock(sent_at)) else {
                return false;
            };
            assert!(
                protocol_ok,
                "the server accepted a Submit the protocol refuses"
            );
            let request = &valid.observation.request;
            assert!(
                validator
                    .spec
                    .check_request(request, &validator.image_limits())
                    .is_ok(),
                "a validated Submit fails the engine's own check"
            );
            decode_images(&request.images, &validator.image_limits()).is_ok()
        }
        Message::FreshObservation(fresh) => {
            let sent_at = fresh.sent_at_us;
            let Ok(valid) = validator.fresh(fresh, clock(sent_at)) else {
                return false;
            };
            assert!(
                protocol_ok,
                "the server accepted an observation the protocol refuses"
            );
            decode_images(&valid.request.images, &validator.image_limits()).is_ok()
        }
        Message::EndTask(end) => {
            let sent_at = end.sent_at_us;
            let accepted = validator.end_task(end, clock(sent_at)).is_ok();
            assert!(
                !accepted || protocol_ok,
                "the server accepted an EndTask the protocol refuses"
            );
            accepted
        }
        Message::Welcome(_)
        | Message::FetchObservation(_)
        | Message::Reply(_)
        | Message::TaskEnded(_)
        | Message::Error(_) => protocol_ok,
    }
}

/// The trace file parser: `data` is a trace file. A file that reads must write back to a file
/// that reads to the same trace set, and the derived quantities the replay uses must be
/// computable.
pub fn trace(data: &[u8]) -> bool {
    let Ok(set) = TraceSet::read(data) else {
        return false;
    };
    for task in &set.tasks {
        let _ = task.execution_seconds();
        for round in &task.rounds {
            let _ = round.aligned_at_action();
        }
    }
    let written = set
        .write(Vec::new())
        .unwrap_or_else(|e| panic!("a trace set that was read does not write: {e}"));
    let again = TraceSet::read(&written[..])
        .unwrap_or_else(|e| panic!("a written trace set does not read back: {e}"));
    let rewritten = again.write(Vec::new()).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        written == rewritten,
        "a trace set changes across a write and read"
    );
    true
}

/// `kairos.toml` parsing: `data` is the file. A config that parses must yield every derived
/// setting the server computes at start-up, and must serialise to a file that parses to the
/// same text again (`kairos init` writes configs).
pub fn config(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let path = Path::new("fuzz/kairos.toml");
    let Ok(config) = Config::parse(text, path) else {
        return false;
    };
    for engine in &config.engines {
        let _ = engine.rtt();
        let _ = engine.options();
    }
    let _ = config.scheduler.core();
    let _ = config.scheduler.refetch_timeout();
    let _ = config.connections.hello_timeout();
    let _ = build_policy(&config.scheduler.policy);
    let written = toml::to_string(&config)
        .unwrap_or_else(|e| panic!("a parsed config does not serialise: {e}"));
    let again = Config::parse(&written, path)
        .unwrap_or_else(|e| panic!("a serialised config does not parse: {e}\n{written}"));
    let rewritten = toml::to_string(&again).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        written == rewritten,
        "a config changes across a write and parse"
    );
    true
}

/// Policy parameter parsing: each line of `data` is a policy spec as `kairos.toml`'s
/// `[scheduler] policy` and `kairos serve --policy` take it (`name:key=value,...`). A spec that
/// parses must print as text that parses to the same spec; its parameters go through the
/// plugin host's conversion (numbers only), then the native priority and horizon policies'
/// own parameter checks and the request path's policy lookup. `true` if some line's parameters
/// built a native policy.
pub fn plugin_params(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let mut built = false;
    for line in text.lines() {
        let Ok(spec) = line.parse::<PolicySpec>() else {
            continue;
        };
        let printed = spec.to_string();
        let again: PolicySpec = printed
            .parse()
            .unwrap_or_else(|e| panic!("a printed spec `{printed}` does not parse: {e}"));
        assert!(
            again == spec,
            "spec `{line}` changes when printed as `{printed}`"
        );
        built |= build_policy(&spec).is_ok();
        let Ok(params): Result<PolicyParams, _> = spec_params(&spec) else {
            continue;
        };
        let native = horizon::builtin(&spec.name, &params).is_ok();
        let requested = actions().build(Some(&spec.name), Some(&params)).is_ok();
        assert_eq!(
            native, requested,
            "`{line}`: a request builds a native policy differently from the registry"
        );
        built |= native;
    }
    built
}

/// Image decoding, as the server does it: `data[0]` picks the format (even: JPEG, odd: PNG)
/// and the rest is the file. The file travels in a `Submit`, is checked from its header by
/// validation, decoded by the bounded decode path, and pooled to the model's features; a
/// decoded image must have the size its header declared, and its features must be in
/// `[-1, 1]`.
pub fn image(data: &[u8]) -> bool {
    let Some((&selector, file)) = data.split_first() else {
        return false;
    };
    let payload = if selector % 2 == 0 {
        ImagePayload::Jpeg {
            data: file.to_vec(),
        }
    } else {
        ImagePayload::Png {
            data: file.to_vec(),
        }
    };
    let Ok(state) = Tensor::from_f32(vec![4], &[0.0; 4]) else {
        panic!("a 4-element state tensor does not build");
    };
    let submit = Submit {
        task: 1,
        round: 1,
        sent_at_us: 1_000,
        observation: Observation {
            captured_at_us: 1_000,
            state,
            images: vec![Image {
                camera: "front".into(),
                payload,
            }],
            instruction: String::new(),
        },
        last_exec: None,
        horizon: None,
        remaining: None,
        control_hz: None,
        attempt: 0,
        seed: None,
        chunking: None,
    };
    let validator = validator();
    let Ok(valid) = validator.submit(submit, RobotId(1), actions(), clock(1_000)) else {
        return false;
    };
    let Ok(decoded) = decode_images(&valid.observation.request.images, &validator.image_limits())
    else {
        return false;
    };
    for image in &decoded {
        let ImageInput::RawU8 {
            height,
            width,
            channels,
            data,
        } = image
        else {
            panic!("a decoded image is not raw u8 pixels");
        };
        assert_eq!(data.len(), height * width * channels, "pixel buffer size");
        let limits = validator.image_limits();
        assert!(
            height * width <= limits.max_pixels,
            "decoded past the pixel cap"
        );
        let features = pooled_features(image, 4)
            .unwrap_or_else(|e| panic!("a decoded image does not pool: {e}"));
        assert!(
            features.iter().all(|v| (-1.0..=1.0).contains(v)),
            "features outside [-1, 1]"
        );
    }
    true
}

/// The openpi endpoint's msgpack decoder (`openpi::msgpack`): `data` is one websocket message.
/// A frame that decodes must encode back to bytes that decode to the same encoding (the
/// decoder neither invents nor drops values), within the same bounds.
pub fn openpi_msgpack(data: &[u8]) -> bool {
    let Ok(value) = msgpack::decode(data, openpi::MAX_VALUES) else {
        return false;
    };
    let mut writer = msgpack::Writer::new();
    writer.value(&value);
    let encoded = writer.finish();
    let again = msgpack::decode(&encoded, openpi::MAX_VALUES)
        .unwrap_or_else(|e| panic!("a re-encoded msgpack value does not decode: {e}"));
    let mut writer = msgpack::Writer::new();
    writer.value(&again);
    assert!(
        writer.finish() == encoded,
        "msgpack encoding is not stable across a round trip"
    );
    // What the key map reads from any value must not panic either.
    let _ = msgpack::NdArray::from_value(&value);
    let _ = msgpack::number_count(&value);
    let _ = msgpack::numbers(&value);
    true
}

/// The openpi key map with its default keys (`observation/image`, `observation/wrist_image`,
/// `observation/state`, `prompt`).
fn openpi_config() -> &'static OpenpiConfig {
    static CONFIG: OnceLock<OpenpiConfig> = OnceLock::new();
    CONFIG.get_or_init(OpenpiConfig::default)
}

/// An openpi request as the endpoint handles it: `data` is one websocket message. It is
/// decoded, mapped through the key map (size checks before any copy or transpose), built into
/// a `Submit` and validated as the endpoint does, and its images decoded. Whatever the key map
/// accepted must be within the limits it checked: every image passes the protocol's raw-image
/// checks with a byte length that matches its shape, and the state fits `max_state_len`.
pub fn openpi_observation(data: &[u8]) -> bool {
    let validator = validator();
    let limits = &validator.limits;
    let Ok(dict) = msgpack::decode(data, openpi::MAX_VALUES) else {
        return false;
    };
    let config = openpi_config();
    let Ok(mut observation) = observation::observation(&dict, config, 1_000, limits) else {
        return false;
    };
    assert!(
        observation.state.shape.iter().product::<u32>() <= limits.max_state_len,
        "the key map built a state over max_state_len"
    );
    assert!(
        observation.images.len() <= limits.max_images as usize,
        "the key map built more images than max_images"
    );
    for image in &observation.images {
        let ImagePayload::Raw { tensor } = &image.payload else {
            panic!("the key map built an image that is not raw");
        };
        assert!(
            tensor.check_len().is_ok(),
            "the key map built an image whose bytes do not match its shape"
        );
        assert!(
            check_raw_image(&image.camera, &tensor.shape, tensor.dtype, limits).is_ok(),
            "the key map built an image over the limits it checked"
        );
    }
    observation::name_cameras(&mut observation, config, &validator.spec.cameras);
    let submit = Submit {
        task: 1,
        round: 0,
        sent_at_us: 1_000,
        observation,
        last_exec: None,
        chunking: None,
        horizon: Some(HorizonSelection {
            policy: "static".into(),
            params: BTreeMap::from([("h".to_string(), validator.spec.chunk_len as f64)]),
            samples: 1,
        }),
        remaining: None,
        attempt: 0,
        control_hz: None,
        seed: None,
    };
    let Ok(valid) = validator.submit(submit, RobotId(1), actions(), clock(1_000)) else {
        return false;
    };
    decode_images(&valid.observation.request.images, &validator.image_limits()).is_ok()
}

/// The worker protocol (`kairos_protocol::worker`), every message: `data` is a frame stream on
/// a worker connection. The first frame is decoded with the worker protocol's frame limit and
/// must re-encode stably (as `wire`); then it goes where each side takes it: a `Register`'s
/// profile into the scheduler's engine profile and the batch deadlines it sets, a `RunBatch`'s
/// requests into the worker's model requests and the model's own check, a `Chunks`' results
/// into the scheduler's chunks.
pub fn worker(data: &[u8]) -> bool {
    let Ok((message, used)) = WorkerMessage::decode_from(data, WORKER_MAX_FRAME) else {
        return false;
    };
    assert!(
        used <= data.len(),
        "the decoder used bytes it was not given"
    );
    let encoded = message
        .encode(u32::MAX)
        .unwrap_or_else(|e| panic!("a decoded {:?} does not encode: {e}", message.kind()));
    let (again, again_used) = WorkerMessage::decode_from(&encoded, u32::MAX)
        .unwrap_or_else(|e| panic!("a re-encoded {:?} does not decode: {e}", message.kind()));
    assert_eq!(
        again_used,
        encoded.len(),
        "a re-encoded frame has trailing bytes"
    );
    let reencoded = again.encode(u32::MAX).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        reencoded == encoded,
        "encoding is not stable across a round trip"
    );
    let validator = validator();
    let spec = &validator.spec;
    match message {
        WorkerMessage::Register(register) => {
            let _ = model_spec(&register.model);
            let Ok(profile) = profile_from_wire(register.profile) else {
                return false;
            };
            let workers = WorkersConfig::default();
            for batch in 1..=profile.max_batch.clamp(1, 64) {
                let _ = workers.batch_deadline(profile.latency(batch));
            }
            true
        }
        WorkerMessage::RunBatch(batch) => {
            let mut served = true;
            for request in batch.requests {
                let Ok(request) = request_from_wire(request) else {
                    served = false;
                    continue;
                };
                served &= spec
                    .check_request(&request, &validator.image_limits())
                    .is_ok();
            }
            served
        }
        WorkerMessage::Chunks(chunks) => {
            let mut usable = true;
            for result in chunks.results {
                match (result.chunk, result.error) {
                    (Some(chunk), None) => {
                        let Ok(chunk) = chunk_from_wire(spec, 1, &chunk) else {
                            usable = false;
                            continue;
                        };
                        let request = ActionRequest {
                            cameras: Vec::new(),
                            state: vec![0.0; spec.state_dim],
                            images: Vec::new(),
                            instruction: String::new(),
                            samples: 1,
                            seed: 0,
                            guidance: None,
                        };
                        usable &= check_output("fuzz", spec, &[request], &[chunk]).is_ok();
                    }
                    (None, Some(_)) => {}
                    _ => usable = false,
                }
            }
            usable
        }
        WorkerMessage::Registered(registered) => {
            let _ = std::time::Duration::from_millis(u64::from(registered.heartbeat_ms));
            true
        }
        WorkerMessage::Refused(_) | WorkerMessage::Heartbeat(_) | WorkerMessage::Drain(_) => true,
    }
}

/// The metrics listener's request heads (`crate::metrics::http`): `data` is what a client
/// sends, up to the listener's [`MAX_HEAD`](crate::metrics::http::MAX_HEAD). The listener
/// parses after every read, so the verdict on any prefix must hold for the whole: a complete
/// head stays the same head and a refusal stays that refusal (`data[0]` picks the cut). The
/// answer must be a well-formed HTTP/1.1 response whose `Content-Length` is its body's length
/// (none for `HEAD`). `true` if it was answered 200.
pub fn http(data: &[u8]) -> bool {
    use crate::metrics::fleet::FleetView;
    use crate::metrics::http::{MAX_HEAD, Parsed, answer, parse};
    use crate::metrics::{Metrics, Readiness};

    static SITE: OnceLock<(Metrics, Readiness, Option<FleetView>)> = OnceLock::new();
    let (metrics, ready, fleet) = SITE.get_or_init(|| {
        let metrics = Metrics::new();
        let ready = Readiness::new();
        ready.set(true);
        let fleet = FleetView::new(metrics.clone(), ready.clone());
        (metrics, ready, fleet)
    });
    let data = &data[..data.len().min(MAX_HEAD)];
    let whole = parse(data);
    let cut = data.first().map_or(0, |&b| usize::from(b).min(data.len()));
    match parse(&data[..cut]) {
        Parsed::Partial => {}
        Parsed::Request { len, .. } => {
            assert!(
                len <= cut,
                "a head longer than the bytes it was parsed from"
            );
            assert_eq!(
                parse(&data[..cut]),
                whole,
                "more bytes changed a complete head"
            );
        }
        refused @ Parsed::Refused(_) => {
            assert_eq!(refused, whole, "more bytes changed a refusal");
        }
    }
    let response = answer(
        whole.clone(),
        data.len(),
        metrics,
        ready,
        fleet.as_ref(),
        std::time::Instant::now(),
    );
    let bytes = response.to_bytes();
    let mut headers = [httparse::EMPTY_HEADER; 16];
    let mut parsed = httparse::Response::new(&mut headers);
    let Ok(httparse::Status::Complete(head_len)) = parsed.parse(&bytes) else {
        panic!("the answer to {whole:?} is not an HTTP response");
    };
    assert_eq!(parsed.code, Some(response.status));
    assert!(
        matches!(response.status, 200 | 400 | 404 | 405 | 431 | 503),
        "unexpected status {}",
        response.status
    );
    let length = parsed
        .headers
        .iter()
        .find(|h| h.name.eq_ignore_ascii_case("content-length"))
        .and_then(|h| std::str::from_utf8(h.value).ok()?.parse::<usize>().ok())
        .unwrap_or_else(|| panic!("no Content-Length in the answer to {whole:?}"));
    let head_only = matches!(
        whole,
        Parsed::Request {
            head_only: true,
            ..
        }
    );
    let body = bytes.len() - head_len;
    if head_only {
        assert_eq!(body, 0, "a HEAD answer carries a body");
    } else {
        assert_eq!(body, length, "Content-Length is not the body's length");
    }
    response.status == 200
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_target_is_named_once() {
        let mut names: Vec<&str> = TARGETS.iter().map(|(name, _)| *name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), TARGETS.len());
    }
}
