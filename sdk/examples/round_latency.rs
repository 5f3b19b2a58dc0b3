//! Sequential round latency through the Rust SDK: the Rust side of the Python package's
//! benchmark (`sdk/python/benches/round_latency.py`, which runs this and the same rounds through
//! `kairos.Client` against one server, and prints both).
//!
//! ```sh
//! cargo run -p kairos-sdk --example round_latency -- 127.0.0.1:4433 kairos-data 200 64
//! ```
//!
//! Arguments: server address, data directory, rounds, side of the square RGB camera image. One
//! task, one round at a time with Last Exec Info, each with a fresh observation (the state, one raw `side × side × 3`
//! u8 image, an instruction); prints, for each round after 10 warm-up rounds, its latency (from
//! `submit` to its reply) and the server's `timing.total_us` (arrival to reply sent), µs.

use std::path::Path;
use std::time::Instant;

use kairos_sdk::protocol::{Image, ImagePayload, Observation, TaskOutcome, Tensor};
use kairos_sdk::robot::ChunkExecutor;
use kairos_sdk::{BlockingClient, ClientConfig, NoRefetch, RoundRequest, data_dir};

const WARM_UP: usize = 10;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() != 4 || args.iter().any(|a| a == "--help" || a == "-h") {
        eprintln!("usage: round_latency SERVER DATA_DIR ROUNDS IMAGE_SIDE");
        std::process::exit(if args.iter().any(|a| a == "--help" || a == "-h") {
            0
        } else {
            2
        });
    }
    let dir = Path::new(&args[1]);
    let rounds: usize = args[2].parse()?;
    let side: u32 = args[3].parse()?;
    let config = ClientConfig::pinned(
        args[0].parse()?,
        data_dir::read_pin(dir)?,
        data_dir::read_token(dir, data_dir::DEFAULT_ROBOT)?,
    );
    let client = BlockingClient::connect(config)?;
    let state_dim = client.welcome().map_or(0, |w| w.model.state_dim);
    let mut task = client.task(rand::random::<u64>() >> 12);
    // Last Exec Info as a robot sends it (and as the Python package does, with the same rules): the
    // server treats a round without it as a task's first, which it serves differently.
    let mut executor = ChunkExecutor::new(30.0, 0.5);
    for round in 0..WARM_UP + rounds {
        // The same observation the Python side builds: a linspace state, a flat grey image.
        let state: Vec<f32> = (0..state_dim)
            .map(|i| i as f32 / (state_dim.max(2) - 1) as f32 + 0.01 * round as f32)
            .collect();
        let pixels = vec![(round % 256) as u8; (side * side * 3) as usize];
        let observation = Observation {
            captured_at_us: client.now_us(),
            state: Tensor::from_f32(vec![state_dim], &state)?,
            images: vec![Image {
                camera: "front".into(),
                payload: ImagePayload::Raw {
                    tensor: Tensor::from_u8(vec![side, side, 3], pixels)?,
                },
            }],
            instruction: "pick up the cube".into(),
        };
        let started = Instant::now();
        let id = task.next_round();
        let mut request = RoundRequest::new(observation);
        request.last_exec = executor.request_sent(id, client.now_us());
        let done = task.submit(request, &mut NoRefetch)?;
        let actions = done.reply.actions.to_f32()?;
        let dim = done
            .reply
            .actions
            .shape
            .get(1)
            .map_or(1, |&d| d.max(1) as usize);
        executor.reply_arrived(id, actions.chunks(dim).map(<[f32]>::to_vec).collect());
        if round >= WARM_UP {
            let latency = started.elapsed().as_micros();
            println!("{latency} {}", done.reply.timing.total_us);
        }
    }
    task.end(TaskOutcome::Done, None)?;
    client.close();
    Ok(())
}
