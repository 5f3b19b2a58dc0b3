//! [`SimulatedRobot`]: a [`Robot`] with a synthetic joint state and synthetic cameras.

use std::future::Future;

use super::{Robot, RobotError};
use crate::protocol::{Image, ImagePayload, Observation, Tensor};

/// A simulated robot: a synthetic joint state that integrates the actions it is sent and a
/// synthetic camera image, executing by counting. For tests, benchmarks and `kairos robot`.
#[derive(Clone, Debug)]
pub struct SimulatedRobot {
    state: Vec<f32>,
    cameras: Vec<(String, u32, u32)>,
    instruction: String,
    executed: u64,
    observations: u64,
}

impl SimulatedRobot {
    /// A robot with a `state_dim` joint state and `cameras` RGB cameras of `height`×`width`
    /// pixels, sent raw as `u8` (named `front`, `wrist`, then `camera2`, `camera3`, ...).
    pub fn new(state_dim: usize, cameras: usize, height: u32, width: u32) -> SimulatedRobot {
        let name = |i: usize| match i {
            0 => "front".to_owned(),
            1 => "wrist".to_owned(),
            i => format!("camera{i}"),
        };
        SimulatedRobot {
            state: (0..state_dim).map(|i| i as f32 * 0.01).collect(),
            cameras: (0..cameras).map(|i| (name(i), height, width)).collect(),
            instruction: "pick up the cube and place it in the bin".to_owned(),
            executed: 0,
            observations: 0,
        }
    }

    /// Names the cameras as `names` does, in order (the model's names from `Welcome`, for a
    /// model that matches images by name); cameras beyond `names` keep their names.
    pub fn with_camera_names(mut self, names: &[String]) -> SimulatedRobot {
        for ((camera, _, _), name) in self.cameras.iter_mut().zip(names) {
            camera.clone_from(name);
        }
        self
    }

    /// Actions executed so far.
    pub fn executed(&self) -> u64 {
        self.executed
    }

    /// Observations captured so far.
    pub fn observations(&self) -> u64 {
        self.observations
    }

    /// The joint state.
    pub fn state(&self) -> &[f32] {
        &self.state
    }

    fn image(&self, height: u32, width: u32) -> Result<Tensor, RobotError> {
        // A moving gradient, so consecutive frames differ the way a camera's do.
        let shift = (self.executed % 256) as u8;
        let data = (0..height * width * 3)
            .map(|i| (i as u8).wrapping_add(shift))
            .collect();
        Tensor::from_u8(vec![height, width, 3], data).map_err(|error| RobotError(error.to_string()))
    }
}

impl Robot for SimulatedRobot {
    fn get_obs(
        &mut self,
        now_us: u64,
    ) -> impl Future<Output = Result<Observation, RobotError>> + Send {
        self.observations += 1;
        let observation = (|| {
            let images = self
                .cameras
                .iter()
                .map(|(camera, height, width)| {
                    Ok(Image {
                        camera: camera.clone(),
                        payload: ImagePayload::Raw {
                            tensor: self.image(*height, *width)?,
                        },
                    })
                })
                .collect::<Result<Vec<_>, RobotError>>()?;
            let state = Tensor::from_f32(vec![self.state.len() as u32], &self.state)
                .map_err(|error| RobotError(error.to_string()))?;
            Ok(Observation {
                captured_at_us: now_us,
                state,
                images,
                instruction: self.instruction.clone(),
            })
        })();
        std::future::ready(observation)
    }

    fn send_act(&mut self, action: &[f32]) -> impl Future<Output = Result<(), RobotError>> + Send {
        for (joint, delta) in self.state.iter_mut().zip(action) {
            *joint += 0.01 * delta;
        }
        self.executed += 1;
        std::future::ready(Ok(()))
    }
}
