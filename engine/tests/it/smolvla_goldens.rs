//! Reading the `smolvla_tiny` fixture's goldens (`golden/goldens.safetensors` and `meta.json`),
//! for the SmolVLA test modules.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::{Path, PathBuf};

use kairos_engine::weights::Checkpoint;

/// `engine/tests/fixtures/smolvla_tiny`.
pub(crate) fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/smolvla_tiny")
}

/// The golden tensors and their description.
pub(crate) struct Goldens {
    ckpt: Checkpoint,
    bytes: Vec<u8>,
    /// `golden/meta.json`.
    pub(crate) meta: serde_json::Value,
}

impl Goldens {
    /// Read both files of the `smolvla_tiny` fixture.
    pub(crate) fn open() -> Self {
        Self::open_at(&fixture())
    }

    /// Read both files of the fixture in `dir`.
    pub(crate) fn open_at(dir: &Path) -> Self {
        let bytes = std::fs::read(dir.join("golden/goldens.safetensors")).unwrap();
        let meta =
            serde_json::from_str(&std::fs::read_to_string(dir.join("golden/meta.json")).unwrap())
                .unwrap();
        Goldens {
            ckpt: Checkpoint::from_bytes("goldens", bytes.clone()).unwrap(),
            bytes,
            meta,
        }
    }

    /// The shape of `key`.
    pub(crate) fn shape(&self, key: &str) -> Vec<usize> {
        self.ckpt
            .shape(key)
            .unwrap_or_else(|| panic!("no golden `{key}`"))
            .to_vec()
    }

    /// A float tensor (f32 or f64) as f32.
    pub(crate) fn f32(&self, key: &str) -> Vec<f32> {
        self.ckpt.tensor(key, &self.shape(key)).unwrap()
    }

    /// A u8 tensor.
    pub(crate) fn u8(&self, key: &str) -> Vec<u8> {
        self.ckpt.tensor_u8(key, &self.shape(key)).unwrap()
    }

    /// An i64 tensor.
    pub(crate) fn i64(&self, key: &str) -> Vec<i64> {
        let st = safetensors::SafeTensors::deserialize(&self.bytes).unwrap();
        let t = st.tensor(key).unwrap();
        assert_eq!(t.dtype(), safetensors::Dtype::I64, "{key}");
        t.data()
            .chunks_exact(8)
            .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }

    /// LeRobot's own f32-vs-f64 error of `key` (`meta.json`, `lerobot_f32_vs_f64`).
    pub(crate) fn e_lr(&self, key: &str) -> f32 {
        self.meta["lerobot_f32_vs_f64"][key]["max_abs"]
            .as_f64()
            .unwrap_or_else(|| panic!("no error bound for `{key}`")) as f32
    }
}
