//! GEMM throughput of the fast kernels on the SmolVLA expert's shapes, against this core's FMA
//! peak measured in the same run. Single-threaded, and timed in this thread's CPU time (Linux
//! /proc) as well as wall time, so that a shared machine's load cancels out.
//!
//! `cargo run --release -p kairos-engine --example gemm_timing -- [m=50] [bf16]`
//! (`bf16`: weights packed in [`Precision::Bf16`]; `KAIROS_ISA=avx2` picks the AVX2 kernel on
//! an AVX-512 CPU; `HOT=1`: one weight copy, cache-resident; `SHAPE=K,N`: that shape only)

use std::time::Instant;

use kairos_engine::kernels::gemm::gemm;
use kairos_engine::kernels::{Init, Isa, MatMut, MatRef, PackedMatrix, Precision};

fn main() {
    if std::env::args().any(|a| a == "--help" || a == "-h") {
        println!(
            "GEMM throughput of the fast kernels on the SmolVLA expert's shapes vs this core's FMA peak.\n\n\
             Usage: gemm_timing [M] [bf16]   (rows of the activation matrix, default 50; bf16 \
             weights)"
        );
        return;
    }
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let m = args.first().copied().unwrap_or(50);
    let isa = Isa::detect();
    let precision = if std::env::args().any(|a| a == "bf16") {
        Precision::Bf16
    } else {
        Precision::F32
    };
    println!("{isa:?} kernels, {precision:?} weights");
    // `SHAPE=K,N` times that one shape instead of the expert's five.
    let custom: Option<(usize, usize)> = std::env::var("SHAPE").ok().and_then(|s| {
        let (k, n) = s.split_once(',')?;
        Some((k.parse().ok()?, n.parse().ok()?))
    });
    let shapes: Vec<(usize, usize, &str)> = match custom {
        Some((k, n)) => vec![(k, n, "SHAPE")],
        None => vec![
            (720, 1600, "qkv"),
            (720, 960, "q"),
            (960, 720, "o"),
            (720, 4096, "gate_up"),
            (2048, 720, "down"),
        ],
    };
    for &(k, n, what) in &shapes {
        let a: Vec<f32> = (0..m * k).map(|i| (i % 97) as f32 / 97.0).collect();
        let w: Vec<f32> = (0..n * k).map(|i| (i % 89) as f32 / 89.0).collect();
        // 16 copies (one per expert layer), cycled, so the weights stream from DRAM as in the
        // model instead of staying in the last-level cache.
        let copies = if std::env::var_os("HOT").is_some() {
            1
        } else {
            16
        };
        let bs: Vec<PackedMatrix> = (0..copies)
            .map(|_| PackedMatrix::from_linear_weight_in(precision, &w, n, k))
            .collect();
        let mut c = vec![0.0; m * n];
        let reps = (50e9 / (2.0 * (m * k * n) as f64)).ceil() as usize;
        let peak = fma_peak_gflops();
        let (t, cpu) = (Instant::now(), thread_cpu_s());
        for r in 0..reps {
            let (a, c) = (MatRef::dense(&a, m, k), MatMut::dense(&mut c, m, n));
            gemm(isa, a, &bs[r % copies], c, Init::Zero);
        }
        let flop = 2.0 * (m * k * n * reps) as f64;
        let (wall, cpu) = (t.elapsed().as_secs_f64(), thread_cpu_s() - cpu);
        println!(
            "{what:8} m={m} k={k} n={n}: {:6.1} GFLOP/s per CPU-second = {:.0}% of FMA peak {peak:.0} ({:.1} wall)",
            flop / cpu / 1e9,
            100.0 * flop / cpu / 1e9 / peak,
            flop / wall / 1e9
        );
    }
}

/// One core's FMA throughput: 12 independent chains of 256-bit FMAs.
fn fma_peak_gflops() -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        /// `n` rounds of 12 independent FMA chains.
        ///
        /// # Safety
        /// Call only on a CPU with AVX2 and FMA.
        #[target_feature(enable = "avx2,fma")]
        fn chains(n: usize) -> f32 {
            use std::arch::x86_64::*;
            let mut acc = [_mm256_set1_ps(0.0); 12];
            let b = _mm256_set1_ps(0.999_999);
            let c = _mm256_set1_ps(1e-7);
            for _ in 0..n {
                for a in acc.iter_mut() {
                    *a = _mm256_fmadd_ps(*a, b, c);
                }
            }
            let mut out = [0.0f32; 8];
            let s = acc
                .iter()
                .fold(_mm256_setzero_ps(), |s, a| _mm256_add_ps(s, *a));
            // SAFETY: out holds 8 floats.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), s) };
            out[0]
        }
        let n = 100_000_000;
        let t = thread_cpu_s();
        let r = if std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: `chains` needs AVX2 and FMA, both just detected on this CPU.
            unsafe { chains(n) }
        } else {
            0.0
        };
        std::hint::black_box(r);
        return (n * 12 * 16) as f64 / (thread_cpu_s() - t) / 1e9;
    }
    #[allow(unreachable_code)]
    0.0
}

/// CPU time of the calling thread in seconds (Linux /proc, 10 ms resolution).
fn thread_cpu_s() -> f64 {
    kairos_engine::profile::thread_cpu_ms() / 1e3
}
