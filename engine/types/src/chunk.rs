//! The result of one generation: the action chunk and its per-step updates.

/// An action chunk with the diffusion updates that produced it.
///
/// Layouts are row-major and flat so that they cross thread, plugin and wire boundaries without
/// conversion:
/// - `actions`: `[samples][chunk_len][action_dim]`
/// - `updates`: `[samples][steps][chunk_len][action_dim]`, where `updates[s][k]` is the change
///   the `k`-th Euler step applied to sample `s` (`dt_k * v_k`), in the order the steps ran.
/// - `noise`: `[samples][chunk_len][action_dim]`, the initial sample `x_{t=1}`.
///
/// `noise + Σ_k updates[s][k] == actions[s]` up to float rounding.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionChunk {
    /// Number of samples `S` drawn for the same observation (at least 1).
    pub samples: usize,
    /// Number of refinement steps `K`.
    pub steps: usize,
    /// Actions per chunk `N`.
    pub chunk_len: usize,
    /// Dimension of one action `D` (already cut to the robot's real action dim).
    pub action_dim: usize,
    /// Final actions, `[S][N][D]`.
    pub actions: Vec<f32>,
    /// Per-step updates, `[S][K][N][D]`.
    pub updates: Vec<f32>,
    /// Initial noise, `[S][N][D]`.
    pub noise: Vec<f32>,
}

impl ActionChunk {
    /// The final actions of sample `s`, `[N][D]`.
    pub fn sample_actions(&self, s: usize) -> &[f32] {
        let len = self.chunk_len * self.action_dim;
        &self.actions[s * len..(s + 1) * len]
    }

    /// The updates of sample `s`, `[K][N][D]`.
    pub fn sample_updates(&self, s: usize) -> &[f32] {
        let len = self.steps * self.chunk_len * self.action_dim;
        &self.updates[s * len..(s + 1) * len]
    }
}
