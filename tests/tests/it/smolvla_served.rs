//! `kairos serve --model DIR` with a whole LeRobot SmolVLA checkpoint (the engine's
//! `smolvla_tiny` fixture: VLM, expert, processors, tokenizer.json), answering a robot over QUIC
//! that sends camera images and an instruction.

use std::path::PathBuf;

/// The fixture is served as the real policy (`smolvla`, not the stand-in), and a robot's round
/// with a PNG camera image, a state and an instruction gets actions of the fixture's shape.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_a_smolvla_checkpoint_to_a_robot() {
    use kairos_sdk::client::{Client, ClientConfig, NoRefetch, RoundRequest};
    use kairos_sdk::protocol::{Image, ImagePayload, Observation, Tensor};
    use kairos_server::cli::serve::{ServeArgs, config, start_engines};
    use kairos_server::config::DEFAULT_ROBOT;
    use kairos_server::data_dir::DataDir;
    use kairos_server::transport::launch::{Policies, start};

    let fixture =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../engine/tests/fixtures/smolvla_tiny");
    let dir = tempfile::tempdir().unwrap();
    let args = ServeArgs {
        config: None,
        listen: Some("127.0.0.1:0".parse().unwrap()),
        data_dir: Some(dir.path().join("kairos-data")),
        model: Some(fixture.display().to_string()),
        ..ServeArgs::default()
    };
    let config = config(&args).unwrap();
    let pool = tokio::task::spawn_blocking({
        let config = config.clone();
        move || start_engines(&config)
    })
    .await
    .unwrap()
    .unwrap();
    let server = start(&config, pool, Policies::default()).await.unwrap();
    let spec = server.model.clone();
    assert_eq!(spec.name, "smolvla");
    assert_eq!(
        (spec.chunk_len, spec.action_dim, spec.state_dim),
        (16, 6, 7)
    );

    let data_dir = DataDir::new(dir.path().join("kairos-data"));
    let client = Client::connect(ClientConfig::pinned(
        server.local_addr,
        data_dir.read_pin().unwrap(),
        data_dir.token(DEFAULT_ROBOT).unwrap(),
    ))
    .await
    .unwrap();
    let png = std::fs::read(fixture.join("golden/missing.0.top.png")).unwrap();
    let mut task = client.task(1);
    let observation = Observation {
        captured_at_us: client.now_us(),
        state: Tensor::from_f32(vec![7], &[0.1, -0.2, 0.3, 0.4, 0.5, -0.6, 0.7]).unwrap(),
        images: vec![Image {
            camera: "top".into(),
            payload: ImagePayload::Png { data: png },
        }],
        instruction: "put the blue block on the plate".into(),
    };
    let reply = task
        .submit(RoundRequest::new(observation), &mut NoRefetch)
        .await
        .unwrap();
    let h = reply.reply.horizon;
    assert!(h >= 1 && h <= spec.chunk_len);
    assert_eq!(reply.reply.actions.shape, vec![h, spec.action_dim]);
    client.close().await;
    server.shutdown().await;
}
