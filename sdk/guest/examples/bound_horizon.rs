//! Template: a horizon-policy plugin in Rust.
//!
//! "bound": execute the prefix of the chunk whose final-step updates are all at most `bound`
//! (an absolute L2 norm), clamped to the robot's `[h_min, h_max]`. Parameter: `bound`
//! (default 0.05). The same policy is in `templates/c/bound.c` and `templates/python/app.py`.
//!
//! In your own crate: depend on `kairos-guest`, set `crate-type = ["cdylib"]`, then
//!
//! ```text
//! cargo test                                            # the logic, natively
//! rustup target add wasm32-wasip2
//! cargo build --release --target wasm32-wasip2          # the component
//! kairos plugin check target/wasm32-wasip2/release/<name>.wasm --param bound=0.05
//! ```

use kairos_guest::{Chunk, HorizonContext, HorizonError, HorizonPolicy, Params};

/// The "bound" policy.
pub struct Bound;

impl HorizonPolicy for Bound {
    fn choose(
        chunk: &Chunk<'_>,
        ctx: &HorizonContext<'_>,
        params: &Params<'_>,
    ) -> Result<u32, HorizonError> {
        if let Some(name) = params.unknown(&["bound"]) {
            return Err(HorizonError::InvalidParam {
                name: name.into(),
                reason: "unknown parameter (expected: bound)".into(),
            });
        }
        let bound = params.get("bound").unwrap_or(0.05);
        if !(bound.is_finite() && bound >= 0.0) {
            return Err(HorizonError::InvalidParam {
                name: "bound".into(),
                reason: "not a finite number >= 0".into(),
            });
        }
        let last_step = chunk.steps - 1;
        let h = (0..chunk.chunk_len)
            .find(|&n| {
                let norm = chunk
                    .update(0, last_step, n)
                    .iter()
                    .map(|&x| f64::from(x) * f64::from(x))
                    .sum::<f64>()
                    .sqrt();
                // A NaN norm counts as not converged.
                norm.is_nan() || norm > bound
            })
            .unwrap_or(chunk.chunk_len);
        Ok(h.clamp(ctx.h_min, ctx.h_max))
    }
}

kairos_guest::register_horizon_policy!(Bound);

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(last_step_norms: &[f32]) -> (Vec<f32>, Vec<f32>) {
        // K = 2 steps, D = 1: step 0 is all ones, step 1 carries the given norms.
        let n = last_step_norms.len();
        let mut updates = vec![1.0; n];
        updates.extend_from_slice(last_step_norms);
        (updates, vec![0.0; n])
    }

    fn choose(
        norms: &[f32],
        h_min: u32,
        h_max: u32,
        params: &[(String, f64)],
    ) -> Result<u32, HorizonError> {
        let (updates, actions) = chunk(norms);
        let chunk = Chunk {
            samples: 1,
            steps: 2,
            chunk_len: norms.len() as u32,
            action_dim: 1,
            updates: &updates,
            actions: &actions,
        };
        let ctx = HorizonContext {
            h_min,
            h_max,
            control_hz: 30.0,
            round_index: 0,
            recent_horizons: &[],
            load: None,
        };
        Bound::choose(&chunk, &ctx, &Params(params))
    }

    #[test]
    fn cuts_at_the_first_large_final_update() {
        assert_eq!(choose(&[0.01, 0.02, 0.5, 0.01], 1, 4, &[]), Ok(2));
        assert_eq!(choose(&[0.01, 0.02, 0.03, 0.01], 1, 4, &[]), Ok(4));
        assert_eq!(choose(&[0.5, 0.01], 1, 2, &[]), Ok(1), "h_min applies");
        assert_eq!(
            choose(&[0.01, 0.01, 0.01], 1, 2, &[]),
            Ok(2),
            "h_max applies"
        );
        assert_eq!(
            choose(&[0.01, 0.2, 0.3], 1, 3, &[("bound".into(), 0.25)]),
            Ok(2)
        );
    }

    #[test]
    fn refuses_bad_parameters() {
        assert!(matches!(
            choose(&[0.0], 1, 1, &[("bond".into(), 1.0)]),
            Err(HorizonError::InvalidParam { .. })
        ));
        assert!(matches!(
            choose(&[0.0], 1, 1, &[("bound".into(), -1.0)]),
            Err(HorizonError::InvalidParam { .. })
        ));
    }
}
