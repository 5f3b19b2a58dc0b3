//! Encoding and decoding cost of a realistic round request: two 224×224 RGB cameras sent raw
//! (150 KB each) and a 32-dim state, as SmolVLA takes them. Baseline: copying the frame's bytes,
//! the floor any decoder that produces owned buffers pays.
//!
//! `cargo bench -p kairos-sdk --bench codec --profile dev`

#![allow(clippy::unwrap_used, missing_docs)]

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use kairos_sdk::protocol::{
    Image, ImagePayload, Limits, Message, Observation, Submit, Tensor, Validate, encode_body,
};

fn submit() -> Submit {
    let camera = |name: &str| Image {
        camera: name.to_owned(),
        payload: ImagePayload::Raw {
            tensor: Tensor::from_u8(vec![224, 224, 3], vec![97; 224 * 224 * 3]).unwrap(),
        },
    };
    Submit {
        task: 1,
        round: 42,
        sent_at_us: 1_000_000,
        observation: Observation {
            captured_at_us: 999_000,
            state: Tensor::from_f32(vec![32], &[0.25; 32]).unwrap(),
            images: vec![camera("front"), camera("wrist")],
            instruction: "pick up the red cube and put it in the bin".to_owned(),
        },
        last_exec: None,
        horizon: None,
        remaining: None,
        attempt: 0,
        control_hz: None,
        seed: None,
        chunking: None,
    }
}

fn codec(c: &mut Criterion) {
    let submit = submit();
    let limits = Limits::default();
    let bytes = encode_body(&submit, limits.max_frame).unwrap();
    let mut group = c.benchmark_group("submit_2x224x224");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.bench_function("copy_bytes (baseline)", |b| {
        b.iter(|| black_box(bytes.to_vec()))
    });
    group.bench_function("encode", |b| {
        b.iter(|| encode_body(black_box(&submit), limits.max_frame).unwrap())
    });
    group.bench_function("decode", |b| {
        b.iter(|| Message::decode_from(black_box(&bytes), limits.max_frame).unwrap())
    });
    group.bench_function("decode_and_validate", |b| {
        b.iter(|| {
            let (message, _) = Message::decode_from(black_box(&bytes), limits.max_frame).unwrap();
            message.validate(&limits).unwrap();
            message
        })
    });
    group.finish();
}

criterion_group!(benches, codec);
criterion_main!(benches);
