//! SmolVLM's SigLIP vision tower and connector on the engine's CPU kernels.
//!
//! Per image (`[C][S][S]`, values in `[-1, 1]`): the patch conv as one GEMM over unfolded
//! patches, plus the position embedding; `num_hidden_layers` pre-LN encoder layers
//! (`x += out_proj(attn(ln1(x)))`, `x += fc2(gelu_tanh(fc1(ln2(x))))`); the post LayerNorm. The
//! connector then pixel-shuffles the `S/p x S/p` patch grid by `scale_factor` and projects each
//! group of `scale²` patches to the text width (transformers' `SmolVLMConnector`).
//!
//! All images of a batch go through every GEMM together (one row per patch), and attention runs
//! per image and head (in `attention`); since each GEMM output row depends on its own input row
//! only, in a fixed order (see [`crate::kernels::gemm`]), an image gets bit-identical results
//! alone or batched.

mod attention;
mod candle;

pub(crate) use candle::CandleVision;

use std::sync::Mutex;

use super::weights::{NormWeights, VlmWeights};
use crate::EngineError;
use crate::kernels::bf16::round_pairs;
use crate::kernels::gemm::{ActivationRows, gemm_par, gemm_par_pairs};
use crate::kernels::{FreeList, Init, MatMut, MatRef, Pool, Precision, SharedMut, grown, vecmath};
use crate::smolvla::config::VlmConfig;
use crate::smolvla::linear::{Linear, LinearWeights};
use attention::{AttentionIn, AttentionOut, HeadScratch};

/// A view of one prepared camera image: `channels x side x side` floats, row-major, in `[-1, 1]`
/// (after LeRobot's `resize_with_pad` and `x * 2 - 1`).
#[derive(Clone, Copy, Debug)]
pub struct VisionImage<'a> {
    /// Height and width in pixels (images are square, as SmolVLM's connector needs).
    pub side: usize,
    /// `[C][side][side]`.
    pub pixels: &'a [f32],
}

/// What the vision tower computes for each image.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VisionOutput {
    /// Post-LayerNorm encoder output, `[patches][vision hidden]` per image.
    pub hidden: Vec<Vec<f32>>,
    /// Connector output (`embed_image`, before LeRobot's `x sqrt(hidden)`),
    /// `[tokens][text hidden]` per image.
    pub embeddings: Vec<Vec<f32>>,
}

impl VisionOutput {
    fn with_capacity(images: usize) -> Self {
        VisionOutput {
            hidden: Vec::with_capacity(images),
            embeddings: Vec::with_capacity(images),
        }
    }
}

struct VisionLayer {
    norm1: NormWeights,
    /// `[q | k | v]` in one GEMM, with the three biases.
    qkv: Linear,
    out: Linear,
    norm2: NormWeights,
    fc1: Linear,
    fc2: Linear,
}

/// The packed vision tower and connector.
pub(crate) struct CpuVision {
    config: VlmConfig,
    patch: Linear,
    positions: Vec<f32>,
    layers: Vec<VisionLayer>,
    post: NormWeights,
    /// The connector (SmolVLM's, no bias) or PaliGemma's projector (with its bias).
    connector: Linear,
    /// The precision of the weight GEMMs, also used for attention's `q kᵀ` and `p v` GEMMs
    /// (keys and values packed in it per request).
    precision: Precision,
    /// The activations of a group, kept between groups and calls (see [`TowerBuffers`]): one
    /// set per group run at the same time.
    buffers: FreeList<TowerBuffers>,
    /// Attention buffers, one set per attention part run at the same time (see
    /// [`HeadScratch`]).
    head_scratch: FreeList<HeadScratch>,
}

/// A group's activations (~40 MB in bf16, ~50 MB in f32, for 1 024 patch rows), kept resident
/// between groups and calls, rather than allocated afresh for every group: each allocation
/// would be zeroed and, coming from `mmap`, faulted in a page at a time. Every value is written
/// before it is read, so reuse changes no result.
#[derive(Default)]
struct TowerBuffers {
    unfolded: Vec<f32>,
    x: Vec<f32>,
    h: Vec<f32>,
    encoder: EncoderBuffers,
    shuffled: Vec<f32>,
    emb: Vec<f32>,
}

/// The encoder layers' activations (see [`TowerBuffers`]).
#[derive(Default)]
struct EncoderBuffers {
    qkv: Vec<f32>,
    /// `qkv` rounded to bf16 pairs, in bf16 mode.
    qkv_pairs: Vec<u32>,
    attn: Vec<f32>,
    attn_pairs: Vec<u32>,
    mlp: Vec<f32>,
    normed: Option<ActivationRows>,
    act: Option<ActivationRows>,
}

/// How a group's images stack into its rows: image `i` is a `grids[i] x grids[i]` patch grid,
/// `counts[i]` rows from row `starts[i]`.
struct GroupRows<'a> {
    grids: &'a [usize],
    counts: Vec<usize>,
    starts: Vec<usize>,
    /// All of them.
    rows: usize,
}

impl<'a> GroupRows<'a> {
    fn new(grids: &'a [usize]) -> Self {
        let counts: Vec<usize> = grids.iter().map(|g| g * g).collect();
        GroupRows {
            grids,
            starts: super::starts(&counts),
            rows: counts.iter().sum(),
            counts,
        }
    }
}

/// `rows` activation rows of `width` in `precision`, reusing `slot`'s where it has room.
fn activation_rows(
    slot: &mut Option<ActivationRows>,
    precision: Precision,
    rows: usize,
    width: usize,
) -> &mut ActivationRows {
    match slot {
        Some(a) if a.fits(precision, rows, width) => {}
        _ => *slot = Some(ActivationRows::new(precision, rows, width)),
    }
    slot.as_mut().expect("set above")
}

impl CpuVision {
    /// Pack `w`, the weight GEMMs in `precision` (already resolved for this CPU), straight from
    /// the stored tensors; each layer's are dropped once packed.
    pub(crate) fn new(w: VlmWeights, precision: Precision) -> Self {
        let layers = w
            .vision_layers
            .into_iter()
            .map(|l| {
                let bias: Vec<f32> = [&l.q_proj, &l.k_proj, &l.v_proj]
                    .iter()
                    .flat_map(|p| p.bias.iter().flatten().copied())
                    .collect();
                VisionLayer {
                    qkv: Linear {
                        w: LinearWeights::pack_stacked(
                            precision,
                            &[&l.q_proj, &l.k_proj, &l.v_proj],
                        ),
                        bias: Some(bias),
                    },
                    norm1: l.norm1,
                    out: l.out_proj.into_linear(precision),
                    norm2: l.norm2,
                    fc1: l.fc1.into_linear(precision),
                    fc2: l.fc2.into_linear(precision),
                }
            })
            .collect();
        CpuVision {
            patch: w.patch_embedding.into_linear(precision),
            positions: w.position_embedding,
            layers,
            post: w.post_layernorm,
            connector: w.connector.into_linear(precision),
            config: w.config,
            precision,
            buffers: FreeList::default(),
            head_scratch: FreeList::default(),
        }
    }

    /// Run the tower and the connector on `images`.
    pub(crate) fn forward(
        &self,
        pool: &Pool,
        images: &[VisionImage<'_>],
    ) -> Result<VisionOutput, EngineError> {
        let grids = validate(&self.config, images)?;
        // Consecutive images whose patches fit in one group (see [`GROUP_ROWS`]).
        let mut groups = Vec::new();
        let mut first = 0;
        while first < images.len() {
            let mut end = first + 1;
            let mut rows = grids[first] * grids[first];
            while end < images.len() && rows + grids[end] * grids[end] <= GROUP_ROWS {
                rows += grids[end] * grids[end];
                end += 1;
            }
            groups.push(first..end);
            first = end;
        }
        let threads = pool.threads().max(1);
        // While there is a group for every thread, each thread runs whole groups on its own
        // (the GEMMs inside run inline): no thread waits for another at each of the tower's
        // ~100 parallel regions per group, and the serial steps (unfolding, pixel shuffle) run
        // in parallel too. The remaining groups split every GEMM over the threads. Which
        // thread computes a row never changes its bits, so both ways give the same results.
        let spread = if threads > 1 {
            groups.len() / threads * threads
        } else {
            0
        };
        let mut outs: Vec<VisionOutput> = Vec::with_capacity(groups.len());
        if spread > 0 {
            let done: Vec<Mutex<Option<VisionOutput>>> =
                (0..spread).map(|_| Mutex::new(None)).collect();
            pool.run(spread, |g| {
                let mut buffers = self.buffers.take(TowerBuffers::default);
                let range = groups[g].clone();
                let mut out = VisionOutput::with_capacity(range.len());
                let (group, group_grids) = (&images[range.clone()], &grids[range]);
                self.forward_group(pool, group, group_grids, &mut buffers, &mut out);
                self.buffers.put(buffers);
                *done[g].lock().unwrap_or_else(|e| e.into_inner()) = Some(out);
            });
            for slot in done {
                let out = slot.into_inner().unwrap_or_else(|e| e.into_inner());
                outs.push(out.expect("every spread group ran"));
            }
        }
        if spread < groups.len() {
            let mut buffers = self.buffers.take(TowerBuffers::default);
            for range in &groups[spread..] {
                let mut out = VisionOutput::with_capacity(range.len());
                let (group, group_grids) = (&images[range.clone()], &grids[range.clone()]);
                self.forward_group(pool, group, group_grids, &mut buffers, &mut out);
                outs.push(out);
            }
            self.buffers.put(buffers);
        }
        let mut out = VisionOutput::with_capacity(images.len());
        for group in outs {
            out.hidden.extend(group.hidden);
            out.embeddings.extend(group.embeddings);
        }
        Ok(out)
    }

    /// Run the tower and the connector on `images` (validated, `grids` patches per side) as one
    /// batch, appending each image's outputs to `out`.
    fn forward_group(
        &self,
        pool: &Pool,
        images: &[VisionImage<'_>],
        grids: &[usize],
        buffers: &mut TowerBuffers,
        out: &mut VisionOutput,
    ) {
        let v = &self.config.vision_config;
        let group = GroupRows::new(grids);
        if group.rows == 0 {
            for _ in images {
                out.hidden.push(Vec::new());
                out.embeddings.push(Vec::new());
            }
            return;
        }
        let TowerBuffers {
            unfolded,
            x,
            h,
            encoder,
            shuffled,
            emb,
        } = buffers;
        let x = grown(x, group.rows * v.hidden_size);
        self.embed_patches(pool, images, &group, unfolded, x);
        for layer in &self.layers {
            self.encoder_layer(pool, &group, layer, encoder, x);
        }
        let h = grown(h, group.rows * v.hidden_size);
        layer_norm_par(pool, x, &self.post, v.layer_norm_eps as f32, h);
        self.connect(pool, &group, h, (shuffled, emb), out);
    }

    /// `x` = the patch embeddings of the group's images: the patch conv as one GEMM over the
    /// unfolded patches (`unfolded` holds them), plus the position embedding.
    fn embed_patches(
        &self,
        pool: &Pool,
        images: &[VisionImage<'_>],
        group: &GroupRows<'_>,
        unfolded: &mut Vec<f32>,
        x: &mut [f32],
    ) {
        let v = &self.config.vision_config;
        let (vh, p, c) = (v.hidden_size, v.patch_size, v.num_channels);
        // Unfold every patch to `[C][p][p]` (the conv weight's order).
        let kdim = c * p * p;
        let unfolded = grown(unfolded, group.rows * kdim);
        for ((im, &g), &start) in images.iter().zip(group.grids).zip(&group.starts) {
            for py in 0..g {
                for px in 0..g {
                    let row = &mut unfolded[(start + py * g + px) * kdim..][..kdim];
                    for ch in 0..c {
                        for ky in 0..p {
                            let src = (ch * im.side + py * p + ky) * im.side + px * p;
                            row[(ch * p + ky) * p..][..p].copy_from_slice(&im.pixels[src..src + p]);
                        }
                    }
                }
            }
        }
        let (patches, rows) = (
            MatRef::dense(unfolded, group.rows, kdim),
            MatMut::dense(x, group.rows, vh),
        );
        gemm_par(pool, patches, &self.patch.w, rows, self.patch.init());
        // Position embedding, per transformers' bucketised fractional coordinates.
        let per_side = v.image_size / p;
        for (&g, &start) in group.grids.iter().zip(&group.starts) {
            let ids = position_ids(g, per_side);
            for (t, &id) in ids.iter().enumerate() {
                let row = &mut x[(start + t) * vh..][..vh];
                vecmath::add_assign(pool.isa(), row, &self.positions[id * vh..][..vh]);
            }
        }
    }

    /// One pre-LN encoder layer on the group's rows `x`:
    /// `x += out_proj(attn(ln1(x)))`, then `x += fc2(gelu_tanh(fc1(ln2(x))))`.
    fn encoder_layer(
        &self,
        pool: &Pool,
        group: &GroupRows<'_>,
        layer: &VisionLayer,
        buffers: &mut EncoderBuffers,
        x: &mut [f32],
    ) {
        let v = &self.config.vision_config;
        let (vh, inter, rows, isa) = (v.hidden_size, v.intermediate_size, group.rows, pool.isa());
        let eps = v.layer_norm_eps as f32;
        // In bf16 (with whole pairs per head) each head's output rows are rounded straight into
        // the out projection's `A`.
        let hd = vh / v.num_attention_heads;
        let pairs_out = self.precision == Precision::Bf16 && hd.is_multiple_of(2);
        let EncoderBuffers {
            qkv,
            qkv_pairs,
            attn,
            attn_pairs,
            mlp,
            normed,
            act,
        } = buffers;
        // The layer norms and the GELU make the `A` of the GEMM they feed row by row (in bf16
        // rounded as they go, see `ActivationRows`).
        let normed = activation_rows(normed, self.precision, rows, vh);
        let act = activation_rows(act, self.precision, rows, inter);
        // Layer norm of every row of `x`; then, while the row is in L1, the bias of the
        // residual GEMM that accumulates into `x` next is added to it (`x += bias + A · B`
        // in that order, as `Init::AccumulateBias` would, without a pass of its own over `x`).
        let norm = |x: &mut [f32],
                    norm: &NormWeights,
                    bias: Option<&[f32]>,
                    normed: &mut ActivationRows| {
            let shared = SharedMut::new(x);
            normed.fill(pool, rows, |r, out| {
                // SAFETY: `fill` hands each row to one part only, and `x` (rows x vh) outlives
                // the call.
                let row = unsafe { std::slice::from_raw_parts_mut(shared.ptr().add(r * vh), vh) };
                vecmath::layer_norm(isa, row, &norm.weight, &norm.bias, eps, out);
                if let Some(bias) = bias {
                    vecmath::add_assign(isa, row, bias);
                }
            });
        };
        norm(x, &layer.norm1, layer.out.bias.as_deref(), normed);
        let qkv = grown(qkv, rows * 3 * vh);
        let qkv_rows = MatMut::dense(qkv, rows, 3 * vh);
        normed.gemm_par(pool, &layer.qkv.w, qkv_rows, layer.qkv.init());
        let residual = MatMut::dense(x, rows, vh);
        if !pairs_out {
            let attn = grown(attn, rows * vh);
            let (src, out) = (AttentionIn::F32(qkv), AttentionOut::F32(attn));
            self.attention(pool, src, &group.counts, &group.starts, out);
            let attn = MatRef::dense(attn, rows, vh);
            gemm_par(pool, attn, &layer.out.w, residual, Init::Accumulate);
        } else {
            // In bf16 the attention reads `q`, `k` and `v` rounded once, row by row, into
            // pairs, rather than rounding each head's queries per block and packing its keys
            // and values from the f32 rows (reading every head's columns down all the rows,
            // three times a head). `3 vh` is even, so no pair straddles two rows: the rows
            // round as one run.
            let qkv_pairs = grown(qkv_pairs, rows * 3 * vh / 2);
            pool.for_row_chunks(qkv_pairs, 3 * vh / 2, |r0, chunk| {
                round_pairs(isa, &qkv[r0 * 3 * vh..][..2 * chunk.len()], chunk);
            });
            let attn_pairs = grown(attn_pairs, rows * vh / 2);
            let (src, out) = (
                AttentionIn::Pairs(qkv_pairs),
                AttentionOut::Pairs(attn_pairs),
            );
            self.attention(pool, src, &group.counts, &group.starts, out);
            let attn = MatRef::dense(attn_pairs, rows, vh / 2);
            gemm_par_pairs(pool, attn, &layer.out.w, residual, Init::Accumulate);
        }
        norm(x, &layer.norm2, layer.fc2.bias.as_deref(), normed);
        let mlp = grown(mlp, rows * inter);
        let mlp_rows = MatMut::dense(mlp, rows, inter);
        normed.gemm_par(pool, &layer.fc1.w, mlp_rows, layer.fc1.init());
        act.fill(pool, rows, |r, out| {
            let row = &mlp[r * inter..(r + 1) * inter];
            // In bf16 the GEMM rounds these to 2^-9: a GELU good to 1e-5 costs less.
            match self.precision {
                Precision::Bf16 => vecmath::gelu_tanh_bf16_grade(isa, row, out),
                Precision::F32 => vecmath::gelu_tanh(isa, row, out),
            }
        });
        act.gemm_par(
            pool,
            &layer.fc2.w,
            MatMut::dense(x, rows, vh),
            Init::Accumulate,
        );
    }

    /// The connector on the post-LayerNorm rows `h`: pixel shuffle (into `shuffled`), then one
    /// GEMM for all images (into `emb`); each image's `h` rows and embeddings go to `out`.
    fn connect(
        &self,
        pool: &Pool,
        group: &GroupRows<'_>,
        h: &[f32],
        (shuffled, emb): (&mut Vec<f32>, &mut Vec<f32>),
        out: &mut VisionOutput,
    ) {
        let vh = self.config.vision_config.hidden_size;
        let s = self.config.scale_factor;
        let wide = vh * s * s;
        let tokens: Vec<usize> = group.grids.iter().map(|g| (g / s) * (g / s)).collect();
        let total: usize = tokens.iter().sum();
        let shuffled = grown(shuffled, total * wide);
        let mut t0 = 0;
        for (&g, &start) in group.grids.iter().zip(&group.starts) {
            let n = g / s;
            for i2 in 0..n {
                for j2 in 0..n {
                    let dst = &mut shuffled[(t0 + i2 * n + j2) * wide..][..wide];
                    for b in 0..s {
                        for a in 0..s {
                            let patch = (i2 * s + b) * g + j2 * s + a;
                            dst[(b * s + a) * vh..][..vh]
                                .copy_from_slice(&h[(start + patch) * vh..][..vh]);
                        }
                    }
                }
            }
            t0 += n * n;
        }
        let th = self.connector.w.n();
        let emb = grown(emb, total * th);
        let (groups, tokens_out) = (
            MatRef::dense(shuffled, total, wide),
            MatMut::dense(emb, total, th),
        );
        gemm_par(
            pool,
            groups,
            &self.connector.w,
            tokens_out,
            self.connector.init(),
        );
        let mut t0 = 0;
        for ((&n, &start), &tk) in group.counts.iter().zip(&group.starts).zip(&tokens) {
            out.hidden.push(h[start * vh..(start + n) * vh].to_vec());
            out.embeddings.push(emb[t0 * th..(t0 + tk) * th].to_vec());
            t0 += tk;
        }
    }
}

/// Patches per side of each image, or an error naming the first image the tower cannot take
/// (a side that is not a multiple of `patch_size x scale_factor`, or the wrong pixel count).
pub(crate) fn validate(
    config: &VlmConfig,
    images: &[VisionImage<'_>],
) -> Result<Vec<usize>, EngineError> {
    let v = &config.vision_config;
    let (c, s) = (v.num_channels, config.scale_factor);
    images
        .iter()
        .enumerate()
        .map(|(i, im)| {
            let side = im.side;
            if side == 0
                || !side.is_multiple_of(v.patch_size)
                || !(side / v.patch_size).is_multiple_of(s)
            {
                return Err(EngineError::InvalidInput(format!(
                    "images[{i}]: side {side} must be a multiple of patch_size {} x scale_factor {s}",
                    v.patch_size
                )));
            }
            if im.pixels.len() != c * side * side {
                return Err(EngineError::InvalidInput(format!(
                    "images[{i}]: {} values, expected {c} x {side} x {side}",
                    im.pixels.len(),
                )));
            }
            Ok(side / v.patch_size)
        })
        .collect()
}

/// Tokens the connector makes of a `side x side` image.
pub(crate) fn tokens_per_image(config: &VlmConfig, side: usize) -> usize {
    let n = side / config.vision_config.patch_size / config.scale_factor;
    n * n
}

/// Images run through the tower together while their patches add up to at most this many
/// rows (a single larger image runs alone). Every operation of the tower is per row or per
/// image, so the grouping changes no result; it bounds the activations (a group of one
/// 512 x 512 camera keeps its ~25 MB in the last-level cache) instead of stacking every camera
/// of a batch into activations that spill to memory.
const GROUP_ROWS: usize = 1024;

/// LayerNorm of each row of `x` into `out`, on the pool's threads.
fn layer_norm_par(pool: &Pool, x: &[f32], norm: &NormWeights, eps: f32, out: &mut [f32]) {
    let h = norm.weight.len();
    pool.for_row_chunks(out, h, |r0, rows| {
        vecmath::layer_norm(
            pool.isa(),
            &x[r0 * h..r0 * h + rows.len()],
            &norm.weight,
            &norm.bias,
            eps,
            rows,
        );
    });
}

/// Position ids of a `g x g` patch grid in a tower trained on `per_side x per_side` patches,
/// exactly as `SmolVLMVisionEmbeddings.forward` computes them (full patch mask): fractional
/// coordinates `i * (1/g)` in f32, clamped below 1, bucketised against
/// `arange(1/per_side, 1, 1/per_side)` with `right=True`.
fn position_ids(g: usize, per_side: usize) -> Vec<usize> {
    let step = 1.0 / per_side as f64;
    // torch.arange: length ceil((end - start) / step), values start + i * step (in double).
    let len = ((1.0 - step) / step).ceil().max(0.0) as usize;
    let boundaries: Vec<f32> = (0..len).map(|i| (step + i as f64 * step) as f32).collect();
    let frac_step = 1.0f32 / g as f32;
    let bucket = |i: usize| -> usize {
        let f = (i as f32 * frac_step).min(1.0 - 1e-6);
        // right=True: the number of boundaries <= f.
        boundaries.iter().take_while(|&&b| b <= f).count()
    };
    let coords: Vec<usize> = (0..g).map(bucket).collect();
    let mut ids = Vec::with_capacity(g * g);
    for &h in &coords {
        for &w in &coords {
            ids.push(h * per_side + w);
        }
    }
    ids
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::Isa;
    use crate::smolvla::config::{VlmConfig, VlmTextConfig, VlmVisionConfig};

    /// Images of 1024 patch rows run alone and four of 256 rows run together (see
    /// [`GROUP_ROWS`]); each image's outputs must be exactly those of running it by itself.
    /// The seven images make four groups, which the two threads run a whole group each (see
    /// [`CpuVision::forward`]), while an image by itself is one group whose GEMMs the two
    /// threads split: the two ways must agree bit for bit.
    #[test]
    fn grouping_images_changes_no_bit() {
        let config = VlmConfig {
            text_config: VlmTextConfig {
                hidden_size: 16,
                num_attention_heads: 2,
                num_key_value_heads: 1,
                head_dim: 8,
                rms_norm_eps: 1e-5,
                num_hidden_layers: 1,
                intermediate_size: 32,
                vocab_size: 64,
            },
            vision_config: VlmVisionConfig {
                hidden_size: 16,
                intermediate_size: 32,
                num_hidden_layers: 2,
                num_attention_heads: 2,
                num_channels: 3,
                image_size: 128,
                patch_size: 4,
                hidden_act: "gelu_pytorch_tanh".into(),
                layer_norm_eps: 1e-6,
            },
            scale_factor: 2,
        };
        let sides = [128usize, 64, 64, 64, 64, 128, 64];
        let pixels: Vec<Vec<f32>> = sides
            .iter()
            .enumerate()
            .map(|(i, &side)| crate::sampler::gaussian_noise(50 + i as u64, 0, 3 * side * side))
            .collect();
        let images: Vec<VisionImage<'_>> = sides
            .iter()
            .zip(&pixels)
            .map(|(&side, pixels)| VisionImage { side, pixels })
            .collect();
        for precision in [Precision::F32, Precision::Bf16] {
            let weights = VlmWeights::random(&config, 1, 3).unwrap();
            let vision = CpuVision::new(weights, precision);
            let pool = Pool::with_isa(2, Isa::detect()).unwrap();
            let all = vision.forward(&pool, &images).unwrap();
            assert_eq!(all.hidden.len(), images.len());
            for (i, image) in images.iter().enumerate() {
                let alone = vision.forward(&pool, std::slice::from_ref(image)).unwrap();
                assert_eq!(alone.hidden[0], all.hidden[i], "{precision:?} image {i}");
                assert_eq!(
                    alone.embeddings[0], all.embeddings[i],
                    "{precision:?} image {i}"
                );
            }
        }
    }

    #[test]
    fn position_ids_are_the_grid_at_native_size_and_buckets_otherwise() {
        assert_eq!(position_ids(4, 4), (0..16).collect::<Vec<_>>());
        let ids = position_ids(32, 32);
        assert_eq!(ids[33], 33);
        assert_eq!(ids[1023], 1023);
        // A 2x2 grid on a 4x4 table samples rows/cols 0 and 2.
        assert_eq!(position_ids(2, 4), vec![0, 2, 8, 10]);
    }
}
