//! `kairos serve --model DIR` with a whole LeRobot SmolVLA checkpoint (the engine's
//! `smolvla_tiny` fixture: VLM, expert, processors, tokenizer.json), answering a robot over QUIC
//! that sends camera images and an instruction.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::{Path, PathBuf};

use kairos_core::round::round_seed;
use kairos_engine::{ActionRequest, EngineOptions, ImageFormat, ImageInput};
use kairos_sdk::client::{Client, ClientConfig, ClientError, NoRefetch, RoundReply, RoundRequest};
use kairos_sdk::protocol::{
    ChunkingSelection, ChunkingStrategy, ErrorCode, ErrorReply, Image, ImagePayload, LastExecInfo,
    Observation, Tensor,
};
use kairos_server::config::{Config, DEFAULT_ROBOT, Overrides};
use kairos_server::data_dir::DataDir;
use kairos_server::pool::{ModelSchemes, build_pool};
use kairos_server::transport::launch::{Policies, RunningServer, start};

const STATE: [f32; 7] = [0.1, -0.2, 0.3, 0.4, 0.5, -0.6, 0.7];
const TASK: &str = "put the blue block on the plate";

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../engine/tests/fixtures/smolvla_tiny")
}

/// `kairos serve --model model [--tokenizer tokenizer]`, data in `data`.
async fn serve(
    model: &Path,
    tokenizer: Option<&Path>,
    data: &Path,
) -> anyhow::Result<RunningServer> {
    serve_with_kernels(model, tokenizer, data, None).await
}

/// [`serve`] with the engine's `kernels` set as `kairos.toml` sets it (`None`: the default).
async fn serve_with_kernels(
    model: &Path,
    tokenizer: Option<&Path>,
    data: &Path,
    kernels: Option<&str>,
) -> anyhow::Result<RunningServer> {
    let overrides = Overrides {
        listen: Some("127.0.0.1:0".parse()?),
        data_dir: Some(data.to_path_buf()),
        model: Some(model.display().to_string()),
        tokenizer: tokenizer.map(Path::to_path_buf),
        ..Overrides::default()
    };
    let mut config = Config::load_with(None, &overrides)?;
    if let Some(kernels) = kernels {
        for engine in &mut config.engines {
            engine.kernels = kernels.into();
        }
    }
    let pool = tokio::task::spawn_blocking({
        let config = config.clone();
        move || build_pool(&config.engines, &ModelSchemes::new(), |_| {})
    })
    .await??;
    Ok(start(&config, pool, Policies::default()).await?)
}

async fn connect(server: &RunningServer, data: &Path) -> Client {
    let data_dir = DataDir::new(data);
    Client::connect(ClientConfig::pinned(
        server.local_addr,
        data_dir.read_pin().unwrap(),
        data_dir.token(DEFAULT_ROBOT).unwrap(),
    ))
    .await
    .unwrap()
}

fn png(name: &str) -> Vec<u8> {
    std::fs::read(fixture().join("golden").join(name)).unwrap()
}

/// One round of task `task` with `images` (camera name, PNG bytes) and `state`.
async fn round(
    client: &Client,
    task: u64,
    images: &[(&str, Vec<u8>)],
    state: &[f32],
) -> Result<RoundReply, ClientError> {
    client
        .task(task)
        .submit(
            RoundRequest::new(observation(client, images, state)),
            &mut NoRefetch,
        )
        .await
}

/// An observation captured now with `images` (camera name, PNG bytes) and `state`.
fn observation(client: &Client, images: &[(&str, Vec<u8>)], state: &[f32]) -> Observation {
    Observation {
        captured_at_us: client.now_us(),
        state: Tensor::from_f32(vec![state.len() as u32], state).unwrap(),
        images: images
            .iter()
            .map(|(camera, data)| Image {
                camera: (*camera).into(),
                payload: ImagePayload::Png { data: data.clone() },
            })
            .collect(),
        instruction: TASK.into(),
    }
}

fn server_error(result: Result<RoundReply, ClientError>) -> ErrorReply {
    match result {
        Err(ClientError::Server(reply)) => reply,
        other => panic!("expected a server error, got {other:?}"),
    }
}

/// The fixture is served as the real policy (`smolvla`, not the stand-in), and a robot's round
/// with a PNG camera image, a state and an instruction gets actions of the fixture's shape.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_a_smolvla_checkpoint_to_a_robot() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("kairos-data");
    let server = serve(&fixture(), None, &data).await.unwrap();
    let spec = server.model.clone();
    assert_eq!(spec.name, "smolvla");
    assert_eq!(
        (spec.chunk_len, spec.action_dim, spec.state_dim),
        (16, 6, 7)
    );
    let client = connect(&server, &data).await;
    let reply = round(&client, 1, &[("top", png("missing.0.top.png"))], &STATE)
        .await
        .unwrap();
    let h = reply.reply.horizon;
    assert!(h >= 1 && h <= spec.chunk_len);
    assert_eq!(reply.reply.actions.shape, vec![h, spec.action_dim]);
    client.close().await;
    server.shutdown().await;
}

/// Images are matched to the model's cameras by the names the robot gives them (after the
/// rename map: the fixture renames `top` to `camera1`), not by their order: the same two
/// cameras sent in either order get exactly the actions of the engine given them in the model's
/// order. `Welcome` names the model's cameras. A camera the model lacks, two names for one
/// camera, and a state of the wrong length are each refused with the field named, and the
/// connection goes on serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cameras_are_matched_by_name_over_quic() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("kairos-data");
    let server = serve(&fixture(), None, &data).await.unwrap();
    let client = connect(&server, &data).await;
    let welcome = client.welcome().await.unwrap();
    assert_eq!(
        welcome.model.cameras,
        ["observation.images.camera1", "observation.images.camera2"]
    );

    let (top, side) = (png("pair.0.top.png"), png("pair.0.camera2.png"));
    let in_order = [("top", top.clone()), ("camera2", side.clone())];
    let reversed = [
        ("observation.images.camera2", side.clone()),
        ("observation.images.top", top.clone()),
    ];
    let a = round(&client, 1, &in_order, &STATE).await.unwrap();
    let b = round(&client, 2, &reversed, &STATE).await.unwrap();

    // The engine, given the images positionally in the model's order, with each round's seed
    // (every task's first round is round 0).
    let model = kairos_engine::load_model_with(&fixture(), &EngineOptions::default()).unwrap();
    let encoded = |bytes: &Vec<u8>| ImageInput::Encoded {
        format: ImageFormat::Png,
        bytes: bytes.clone(),
    };
    let expected = |task: u64| {
        let request = ActionRequest {
            state: STATE.to_vec(),
            images: vec![encoded(&top), encoded(&side)],
            cameras: Vec::new(),
            instruction: TASK.into(),
            samples: 1,
            seed: round_seed(task, 0),
            guidance: None,
        };
        model.generate(&[request]).unwrap().remove(0)
    };
    for (task, reply) in [(1, &a), (2, &b)] {
        let want = expected(task);
        let h = reply.reply.horizon as usize;
        let d = want.action_dim;
        assert_eq!(
            reply.reply.actions.to_f32().unwrap(),
            want.sample_actions(0)[..h * d],
            "task {task}"
        );
    }
    // The swapped images really are a different observation: matching by position would
    // have given other actions.
    let swapped = ActionRequest {
        images: vec![encoded(&side), encoded(&top)],
        cameras: Vec::new(),
        state: STATE.to_vec(),
        instruction: TASK.into(),
        samples: 1,
        seed: round_seed(2, 0),
        guidance: None,
    };
    assert_ne!(
        model.generate(&[swapped]).unwrap()[0].sample_actions(0),
        expected(2).sample_actions(0)
    );

    let unknown = server_error(
        round(
            &client,
            3,
            &[("top", top.clone()), ("wrist", side.clone())],
            &STATE,
        )
        .await,
    );
    assert_eq!(unknown.code, ErrorCode::InvalidObservation);
    assert!(
        unknown.message.contains("observation.images[1].camera")
            && unknown.message.contains("`wrist`")
            && unknown
                .message
                .contains("observation.images.camera1, observation.images.camera2"),
        "{}",
        unknown.message
    );
    let twice = server_error(
        round(
            &client,
            4,
            &[
                ("top", top.clone()),
                ("observation.images.camera1", side.clone()),
            ],
            &STATE,
        )
        .await,
    );
    assert_eq!(twice.code, ErrorCode::InvalidObservation);
    assert!(
        twice.message.contains("images[1].camera"),
        "{}",
        twice.message
    );
    let short = server_error(round(&client, 5, &[("top", top.clone())], &STATE[..6]).await);
    assert_eq!(short.code, ErrorCode::InvalidObservation);
    assert!(
        short.message.contains("observation.state") && short.message.contains("needs 7"),
        "{}",
        short.message
    );
    // A missing camera is not an error: it follows `empty_cameras`.
    let only_second = round(&client, 6, &[("camera2", side)], &STATE)
        .await
        .unwrap();
    assert!(only_second.reply.horizon >= 1);
    client.close().await;
    server.shutdown().await;
}

/// `kairos serve --model DIR` looks for the task tokenizer beside the checkpoint; without one
/// there, starting fails with an error naming both places to put it, and `--tokenizer FILE`
/// serves the same checkpoint.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_tokenizer_is_given_or_beside_the_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("my_smolvla");
    std::fs::create_dir(&model).unwrap();
    for entry in std::fs::read_dir(fixture()).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() && path.file_name().is_some_and(|n| n != "tokenizer.json") {
            std::fs::copy(&path, model.join(path.file_name().unwrap())).unwrap();
        }
    }
    let data = dir.path().join("kairos-data");
    let error = format!("{:#}", serve(&model, None, &data).await.err().unwrap());
    assert!(
        error.contains(&model.join("tokenizer.json").display().to_string())
            && error.contains("--tokenizer"),
        "{error}"
    );
    let missing = dir.path().join("nowhere/tokenizer.json");
    let error = format!(
        "{:#}",
        serve(&model, Some(&missing), &data).await.err().unwrap()
    );
    assert!(error.contains("nowhere/tokenizer.json"), "{error}");

    let server = serve(&model, Some(&fixture().join("tokenizer.json")), &data)
        .await
        .unwrap();
    assert_eq!(server.model.name, "smolvla");
    let client = connect(&server, &data).await;
    let reply = round(&client, 1, &[("top", png("missing.0.top.png"))], &STATE)
        .await
        .unwrap();
    assert_eq!(reply.reply.actions.shape[1], 6);
    client.close().await;
    server.shutdown().await;
}

/// `chunking = rtc_vjp` on SmolVLA: a server on the Candle path (`kernels = "candle"`) serves
/// it, also once the robot has committed actions (the round the guidance applies to); a server
/// on the fast kernels refuses it before the round is queued, naming the Candle path.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rtc_vjp_is_served_on_the_candle_path_and_refused_on_the_fast_kernels() {
    let images = [("top", png("missing.0.top.png"))];
    let submit = |client: &Client, last_exec: Option<LastExecInfo>| {
        let mut request = RoundRequest::new(observation(client, &images, &STATE));
        request.chunking = Some(ChunkingSelection::new(ChunkingStrategy::RtcVjp));
        request.control_hz = Some(5.0);
        request.last_exec = last_exec;
        let mut task = client.task(3);
        async move { task.submit(request, &mut NoRefetch).await }
    };

    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("kairos-data");
    let server = serve_with_kernels(&fixture(), None, &data, Some("candle"))
        .await
        .unwrap();
    let client = connect(&server, &data).await;
    let first = submit(&client, None).await.unwrap().reply;
    let started_us = client.now_us();
    let exec = LastExecInfo {
        exec_started_at_us: started_us,
        actions_remaining: first.horizon - 1,
        control_hz: 5.0,
        round: Some(first.round),
        delay: Some(0),
    };
    let second = submit(&client, Some(exec)).await.unwrap().reply;
    assert_eq!(second.chunking.as_deref(), Some("rtc_vjp"));
    assert_eq!(second.actions.shape, vec![second.horizon, 6]);
    client.close().await;
    server.shutdown().await;

    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("kairos-data");
    let server = serve(&fixture(), None, &data).await.unwrap();
    let client = connect(&server, &data).await;
    let refused = server_error(submit(&client, None).await);
    assert_eq!(refused.code, ErrorCode::InvalidRequest);
    assert!(
        refused.message.contains("rtc_vjp") && refused.message.contains("kernels = \"candle\""),
        "{}",
        refused.message
    );
    client.close().await;
    server.shutdown().await;
}
