//! One robot can never hurt another (issue #12, items 1 and 2): a bad observation fails only its
//! own round, with `invalid_observation` naming the field, while the other robots' rounds are
//! answered; a decompression bomb is refused from its header, before any pixel is allocated.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use kairos_engine::ImageInput;
use kairos_engine::image_features::{ImageLimits, MAX_SIDE, check_image, pooled_features};
use kairos_sdk::client::{Client, ClientError, NoRefetch, RoundReply, RoundRequest};
use kairos_sdk::protocol::{ErrorCode, Image, ImagePayload, Limits, Observation, Tensor};
use kairos_tests::harness::{ServerOptions, TestServer, observation};

/// A real, decodable all-black RGB PNG of `width` x `height` in about 13 bits per 258 pixel
/// bytes: one fixed-Huffman deflate block of a zero literal followed by length-258,
/// distance-1 copies. At 8192 x 8192 it is 1.3 MB and inflates to 192 MiB: a decompression bomb.
fn black_png(width: u32, height: u32) -> Vec<u8> {
    struct Bits {
        out: Vec<u8>,
        acc: u64,
        n: u32,
    }
    impl Bits {
        /// `value`'s low `len` bits, least significant first (deflate's bit order).
        fn put(&mut self, value: u32, len: u32) {
            self.acc |= u64::from(value) << self.n;
            self.n += len;
            while self.n >= 8 {
                self.out.push(self.acc as u8);
                self.acc >>= 8;
                self.n -= 8;
            }
        }
        /// A Huffman code, most significant bit first.
        fn code(&mut self, code: u32, len: u32) {
            self.put(code.reverse_bits() >> (32 - len), len);
        }
    }
    let raw_len = u64::from(height) * (1 + 3 * u64::from(width));
    let mut bits = Bits {
        out: vec![0x78, 0x01],
        acc: 0,
        n: 0,
    };
    bits.put(1, 1); // BFINAL
    bits.put(1, 2); // fixed Huffman codes
    bits.code(0x30, 8); // literal 0
    let mut left = raw_len - 1;
    while left >= 258 {
        bits.code(0xc5, 8); // length 258 (code 285)
        bits.code(0, 5); // distance 1
        left -= 258;
    }
    for _ in 0..left {
        bits.code(0x30, 8);
    }
    bits.code(0, 7); // end of block
    bits.put(0, 7); // flush
    let mut zlib = bits.out;
    // Adler-32 of zeros: a = 1, b = the count.
    let adler = ((raw_len % 65521) << 16) as u32 | 1;
    zlib.extend_from_slice(&adler.to_be_bytes());

    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 {
                    0xedb8_8320 ^ (crc >> 1)
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = png.len();
        png.extend_from_slice(kind);
        png.extend_from_slice(data);
        let crc = crc32(&png[start..]);
        png.extend_from_slice(&crc.to_be_bytes());
    };
    let mut header = Vec::new();
    header.extend_from_slice(&width.to_be_bytes());
    header.extend_from_slice(&height.to_be_bytes());
    header.extend_from_slice(&[8, 2, 0, 0, 0]); // 8-bit RGB
    chunk(b"IHDR", &header);
    chunk(b"IDAT", &zlib);
    chunk(b"IEND", &[]);
    png
}

fn png_observation(client: &Client, png: Vec<u8>) -> Observation {
    Observation {
        images: vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Png { data: png },
        }],
        ..observation(client, 0.0)
    }
}

async fn round(
    client: &Client,
    task: u64,
    observation: Observation,
) -> Result<RoundReply, ClientError> {
    client
        .task_from(task, 0)
        .submit(RoundRequest::new(observation), &mut NoRefetch)
        .await
}

fn server_error(result: Result<RoundReply, ClientError>) -> kairos_sdk::protocol::ErrorReply {
    match result {
        Err(ClientError::Server(reply)) => reply,
        other => panic!("expected a server error, got {other:?}"),
    }
}

#[test]
fn the_bomb_generator_makes_a_real_png() {
    let image = ImageInput::Encoded {
        format: kairos_engine::ImageFormat::Png,
        bytes: black_png(37, 5),
    };
    // Fully decodable: all black, so every pooled feature is -1.
    assert_eq!(pooled_features(&image, 2).unwrap(), vec![-1.0; 12]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_observations_fail_only_their_own_rounds() {
    let server = TestServer::start(ServerOptions {
        max_batch: 8,
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let robots: Vec<Client> = {
        let mut robots = Vec::new();
        for _ in 0..4 {
            robots.push(server.connect(&server.token).await.unwrap());
        }
        robots
    };
    let nan_state = |client: &Client| {
        let mut o = observation(client, 0.0);
        o.state = Tensor::from_f32(vec![6], &[0.5, f32::NAN, 0.0, 0.0, 0.0, 0.0]).unwrap();
        o
    };
    let infinite_state = |client: &Client| {
        let mut o = observation(client, 0.0);
        o.state = Tensor::from_f32(vec![6], &[f32::INFINITY; 6]).unwrap();
        o
    };
    let not_a_png = |client: &Client| png_observation(client, b"\xff\xd8\xff\xe0 JFIF".to_vec());
    let nan_pixels = |client: &Client| Observation {
        images: vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Raw {
                tensor: Tensor::from_f32(vec![1, 2, 1], &[0.5, f32::NAN]).unwrap(),
            },
        }],
        ..observation(client, 0.0)
    };
    let zero_wide = |client: &Client| Observation {
        images: vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Raw {
                tensor: Tensor::from_u8(vec![4, 0, 3], Vec::new()).unwrap(),
            },
        }],
        ..observation(client, 0.0)
    };
    type Bad = fn(&Client) -> Observation;
    let cases: [(Bad, &str); 5] = [
        (nan_state, "observation.state[1]"),
        (infinite_state, "observation.state[0]"),
        (not_a_png, "observation.images[0]"),
        (nan_pixels, "observation.images[0]"),
        (zero_wide, "observation.images[0]"),
    ];
    for (case, (bad, field)) in cases.into_iter().enumerate() {
        // One bad round and three good ones, all in flight at once.
        let task = |robot: usize| 1000 * (case as u64 + 1) + robot as u64;
        let good = |i: usize| round(&robots[i], task(i), observation(&robots[i], i as f32));
        let (bad_result, good1, good2, good3) = tokio::join!(
            round(&robots[0], task(0), bad(&robots[0])),
            good(1),
            good(2),
            good(3),
        );
        let error = server_error(bad_result);
        assert_eq!(
            error.code,
            ErrorCode::InvalidObservation,
            "{}",
            error.message
        );
        assert!(!error.retryable, "{}", error.message);
        assert!(
            error.message.contains(field),
            "{} names {field}",
            error.message
        );
        for reply in [good1, good2, good3] {
            assert!(reply.unwrap().reply.horizon > 0);
        }
    }
    for robot in robots {
        robot.close().await;
    }
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_decompression_bomb_is_refused_and_others_are_served() {
    let server = TestServer::start(ServerOptions::default()).await.unwrap();
    let attacker = server.connect(&server.token).await.unwrap();
    let bystander = server.connect(&server.token).await.unwrap();
    let bomb = black_png(8192, 8192);
    assert!(bomb.len() < 2 << 20, "{} bytes", bomb.len());
    let (refused, served) = tokio::join!(
        round(&attacker, 1, png_observation(&attacker, bomb.clone())),
        round(&bystander, 2, observation(&bystander, 0.0)),
    );
    let error = server_error(refused);
    assert_eq!(error.code, ErrorCode::InvalidObservation);
    assert!(!error.retryable);
    assert!(
        error.message.contains("observation.images[0]")
            && error
                .message
                .contains("8192x8192 = 67108864 pixels, over the limit"),
        "{}",
        error.message
    );
    served.unwrap();
    // An image within the cap decodes and is served.
    let fine = round(
        &attacker,
        3,
        png_observation(&attacker, black_png(640, 480)),
    );
    assert!(fine.await.unwrap().reply.horizon > 0);
    attacker.close().await;
    bystander.close().await;
    server.shutdown().await;
}

/// Peak resident memory of this process, KiB (`VmHWM` in /proc/self/status).
fn peak_rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

const RSS_CHILD: &str = "KAIROS_ISOLATION_RSS_CHILD";

/// The peak-memory claim, measured in a process of its own: the test re-runs itself alone,
/// so no other test's allocations move the high-water mark. The child checks the bomb as
/// validation does (the server's default `max_image_pixels`) and hands it to the engine's own
/// image path, and reports how much the peak grew. Before the fix the engine decoded it
/// (8192 is within its side limit) and the peak grew by about 1 GB.
#[test]
fn a_decompression_bomb_allocates_no_pixels() {
    let bomb = ImageInput::Encoded {
        format: kairos_engine::ImageFormat::Png,
        bytes: black_png(8192, 8192),
    };
    if std::env::var_os(RSS_CHILD).is_some() {
        let Some(before) = peak_rss_kib() else {
            println!("rss-growth-kib: unavailable");
            return;
        };
        let started = std::time::Instant::now();
        let limits = ImageLimits {
            max_side: MAX_SIDE,
            max_pixels: Limits::default().max_image_pixels as usize,
        };
        let checked = check_image(&bomb, &limits);
        let pooled = pooled_features(&bomb, 8);
        let elapsed = started.elapsed();
        let after = peak_rss_kib().unwrap_or(u64::MAX);
        println!(
            "refused: {} {}",
            checked.is_err(),
            pooled.as_ref().map(|_| "decoded").unwrap_or("refused")
        );
        println!("refusal-us: {}", elapsed.as_micros());
        println!("rss-growth-kib: {}", after.saturating_sub(before));
        return;
    }
    let exe = std::env::current_exe().unwrap();
    // The test's name as the harness knows it: its module path less the crate's name.
    let name = match module_path!().split_once("::") {
        Some((_, module)) => format!("{module}::a_decompression_bomb_allocates_no_pixels"),
        None => "a_decompression_bomb_allocates_no_pixels".to_owned(),
    };
    let out = std::process::Command::new(exe)
        .args(["--exact", name.as_str(), "--nocapture", "--test-threads=1"])
        .env(RSS_CHILD, "1")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    let value = |key: &str| {
        stdout
            .lines()
            // The harness may print the test's name on the same line first.
            .find_map(|l| l.split_once(key).map(|(_, value)| value))
            .map(str::trim)
            .unwrap_or_else(|| panic!("no {key} in {stdout}"))
            .to_owned()
    };
    let growth = value("rss-growth-kib:");
    if growth == "unavailable" {
        // No procfs (not Linux): the functional checks above still ran in the child.
        return;
    }
    assert_eq!(value("refused:"), "true refused", "{stdout}");
    let growth: u64 = growth.parse().unwrap();
    assert!(
        growth < 50 * 1024,
        "peak RSS grew by {growth} KiB refusing the bomb"
    );
    eprintln!(
        "bomb refused in {} µs, peak RSS growth {growth} KiB",
        value("refusal-us:")
    );
}
