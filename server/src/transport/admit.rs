//! The one path a round request takes into the driver, whatever transport brought it (a QUIC
//! stream, an openpi websocket): the robot's round rate, the validator's checks against the
//! model and limits, image decoding on the bounded decode pool, then [`DriverHandle::submit`](crate::driver::DriverHandle::submit).

use kairos_sdk::protocol::Submit;
use tokio::sync::mpsc;

use super::ServerContext;
use crate::driver::{PendingRound, RefetchAsk};
use crate::validation::RequestError;
use kairos_core::clock_map::ClockMap;
use kairos_core::scheduler::RobotId;
use kairos_core::time::Timestamp;

impl ServerContext {
    /// Validates `submit` from `robot`, decodes its images and hands it to the driver.
    /// `received` is when it was read on the driver's clock; re-fetch asks for it go to `link`
    /// (a link whose receiver is dropped means "this client cannot be asked": the driver then
    /// uses the queued observation at once).
    pub async fn admit(
        &self,
        submit: Submit,
        robot: RobotId,
        clock: ClockMap,
        received: Timestamp,
        link: mpsc::Sender<RefetchAsk>,
    ) -> Result<PendingRound, RequestError> {
        // Before any work: a robot over its round rate costs a bucket lookup.
        self.fairness
            .rounds
            .try_take(robot, super::fairness::now())
            .map_err(|retry_after| RequestError::RateLimited {
                who: format!("robot `{}`", self.robots.name(robot)),
                limit: "rounds_per_s_per_robot",
                retry_after,
            })?;
        let valid = self.validator.submit(submit, robot, &self.actions, clock)?;
        let valid = self.decode.decode_submit(valid).await?;
        self.driver
            .submit(valid, received, link)
            .await
            .map_err(|_| RequestError::SHUTTING_DOWN)
    }
}
