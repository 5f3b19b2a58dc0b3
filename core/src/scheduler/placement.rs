//! Algorithm 1 phase 3 ("shortest estimated delay guided placement"), generalised from one edge
//! and one cloud instance to any number of each.
//!
//! 1. Idle edge instances, nearest first (by RTT, then `EngineId`: local instances have RTT 0,
//!    so they keep `EngineId` order), each take the next `max_batch` requests of the priority
//!    order.
//! 2. Every request still in the order (in priority order) is offloaded to an idle cloud instance
//!    only if `cloud.latency(batch + 1) + cloud.rtt < edge_delay(request)` for the idle cloud
//!    instance with room where the left side is smallest (ties: lowest `EngineId`). A request not
//!    offloaded stays pending and keeps its place in the edge queue.
//! 3. `edge_delay(request)` is the estimated queueing delay before the request would start on the
//!    edge: the edge instances are lanes that become free at the end of their current batch
//!    (`busy_until`, or `now + latency(batch) + rtt` for a batch placed in step 1); each time a lane
//!    frees it takes the next `max_batch` requests that stay on the edge and is busy for
//!    `latency(max_batch) + rtt`. The request's delay is the start of its group minus `now`. With no
//!    edge instance the delay is infinite, so everything that fits goes to the cloud.
//!
//! The comparison is the paper's: cloud latency including the round trip against the *queueing*
//! delay at the edge (not the edge completion time), which keeps placement edge-first.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::time::Duration;

use kairos_engine_types::EngineProfile;

use super::Tier;
use crate::time::Timestamp;

/// One engine instance as placement sees it.
pub(crate) struct EngineSlot<'a> {
    pub tier: Tier,
    /// `profile.max_batch`, at least 1.
    pub max_batch: usize,
    /// `None` when idle; the estimated end of its current batch when busy.
    pub busy_until: Option<Timestamp>,
    pub profile: &'a EngineProfile,
    pub rtt: Duration,
}

impl EngineSlot<'_> {
    /// Latency of a batch of `batch` requests plus the round trip to the instance.
    pub fn cost(&self, batch: usize) -> Duration {
        let batch = u32::try_from(batch).unwrap_or(u32::MAX);
        self.profile.latency(batch).saturating_add(self.rtt)
    }
}

/// Where each request of the order goes.
#[derive(Debug, Default, PartialEq, Eq)]
pub(crate) struct Placement {
    /// Per engine (same indexing as the slots): the pending indices it runs, in priority order.
    pub batches: Vec<Vec<usize>>,
    /// Requests placed on cloud instances.
    pub offloaded: usize,
}

/// Places the requests of `order` (pending indices, most urgent first) on the idle instances.
pub(crate) fn place(now: Timestamp, order: &[usize], engines: &[EngineSlot<'_>]) -> Placement {
    let mut batches: Vec<Vec<usize>> = vec![Vec::new(); engines.len()];
    let mut pos = 0;
    // Nearest first: a remote edge worker's round trip is part of every batch it runs.
    let mut edges: Vec<usize> = (0..engines.len())
        .filter(|&i| engines[i].tier == Tier::Edge)
        .collect();
    edges.sort_by_key(|&i| (engines[i].rtt, i));
    for i in edges {
        let engine = &engines[i];
        if engine.busy_until.is_none() && pos < order.len() {
            let take = engine.max_batch.min(order.len() - pos);
            batches[i].extend_from_slice(&order[pos..pos + take]);
            pos += take;
        }
    }
    let clouds: Vec<usize> = engines
        .iter()
        .enumerate()
        .filter(|(_, e)| e.tier == Tier::Cloud && e.busy_until.is_none())
        .map(|(i, _)| i)
        .collect();
    let mut offloaded = 0;
    if pos < order.len() && !clouds.is_empty() {
        let mut edge = EdgeQueue::new(now, engines, &batches);
        for &request in &order[pos..] {
            let best_cloud = clouds
                .iter()
                .filter(|&&c| batches[c].len() < engines[c].max_batch)
                .map(|&c| (engines[c].cost(batches[c].len() + 1), c))
                .min();
            let Some((cloud_cost, cloud)) = best_cloud else {
                break;
            };
            if cloud_cost < edge.delay_of_next() {
                batches[cloud].push(request);
                offloaded += 1;
            } else {
                edge.keep_next();
            }
        }
    }
    Placement { batches, offloaded }
}

/// The work in hand, in time: how long from `now` until the first engine instance is free
/// again if no new request came. Every instance (edge and cloud) is a lane free at the end of
/// its current batch (`busy_until`, or `now` when idle); `queued` requests then run in full
/// batches, each taken by the lane that frees first and busy for `cost(batch)`. What
/// [`crate::scheduler::ServerLoad::backlog`] reports to horizon policies.
pub(crate) fn backlog(now: Timestamp, queued: usize, engines: &[EngineSlot<'_>]) -> Duration {
    let mut lanes: BinaryHeap<Reverse<(Timestamp, usize)>> = engines
        .iter()
        .enumerate()
        .map(|(i, e)| Reverse((e.busy_until.map_or(now, |until| until.max(now)), i)))
        .collect();
    let mut left = queued;
    while left > 0 {
        let Some(Reverse((free_at, lane))) = lanes.pop() else {
            break;
        };
        let engine = &engines[lane];
        let batch = engine.max_batch.max(1).min(left);
        left -= batch;
        lanes.push(Reverse((free_at + engine.cost(batch), lane)));
    }
    lanes
        .peek()
        .map_or(Duration::ZERO, |Reverse((free_at, _))| {
            free_at.saturating_since(now)
        })
}

/// The simulated edge queue of step 3.
struct EdgeQueue<'a, 'b> {
    now: Timestamp,
    engines: &'a [EngineSlot<'b>],
    /// (time the lane is free, engine index), earliest first.
    lanes: BinaryHeap<Reverse<(Timestamp, usize)>>,
    /// The group being filled: its start and the slots left in it.
    group: Option<(Timestamp, usize)>,
}

impl<'a, 'b> EdgeQueue<'a, 'b> {
    fn new(now: Timestamp, engines: &'a [EngineSlot<'b>], placed: &[Vec<usize>]) -> Self {
        let lanes = engines
            .iter()
            .enumerate()
            .filter(|(_, e)| e.tier == Tier::Edge)
            .map(|(i, e)| {
                let free_at = match e.busy_until {
                    Some(until) => until.max(now),
                    None if placed[i].is_empty() => now,
                    None => now + e.cost(placed[i].len()),
                };
                Reverse((free_at, i))
            })
            .collect();
        EdgeQueue {
            now,
            engines,
            lanes,
            group: None,
        }
    }

    /// Queueing delay of the next request if it stays on the edge (`Duration::MAX` without edge
    /// instances).
    fn delay_of_next(&mut self) -> Duration {
        if !matches!(self.group, Some((_, left)) if left > 0) {
            let Some(Reverse((free_at, lane))) = self.lanes.pop() else {
                return Duration::MAX;
            };
            let engine = &self.engines[lane];
            self.lanes
                .push(Reverse((free_at + engine.cost(engine.max_batch), lane)));
            self.group = Some((free_at, engine.max_batch));
        }
        match self.group {
            Some((start, _)) => start.saturating_since(self.now),
            None => Duration::MAX,
        }
    }

    /// The next request stays on the edge: it takes a slot of the current group.
    fn keep_next(&mut self) {
        if let Some((_, left)) = self.group.as_mut() {
            *left = left.saturating_sub(1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kairos_engine_types::ProfilePoint;

    fn profile(ms_per_batch: &[(u32, f64)], max_batch: u32) -> EngineProfile {
        EngineProfile {
            model: "m".into(),
            device: "d".into(),
            points: ms_per_batch
                .iter()
                .map(|&(batch, latency_ms)| ProfilePoint { batch, latency_ms })
                .collect(),
            max_batch,
        }
    }

    fn t(ms: u64) -> Timestamp {
        Timestamp::from_micros(ms * 1_000)
    }

    #[test]
    fn backlog_is_the_time_until_an_engine_frees_after_the_queue() {
        let p = profile(&[(1, 10.0), (2, 20.0), (4, 40.0)], 4);
        let slot = |busy_until| EngineSlot {
            tier: Tier::Edge,
            max_batch: 4,
            busy_until,
            profile: &p,
            rtt: Duration::ZERO,
        };
        let idle = [slot(None)];
        assert_eq!(
            backlog(t(100), 0, &idle),
            Duration::ZERO,
            "idle, nothing queued"
        );
        assert_eq!(backlog(t(100), 1, &idle), Duration::from_millis(10));
        // 6 queued on one lane: a full batch of 4 (40 ms), then 2 (20 ms).
        assert_eq!(backlog(t(100), 6, &idle), Duration::from_millis(60));
        let busy = [slot(Some(t(130)))];
        assert_eq!(backlog(t(100), 0, &busy), Duration::from_millis(30));
        assert_eq!(backlog(t(100), 4, &busy), Duration::from_millis(70));
        // Two lanes: the idle one takes the queue, the busy one frees first.
        let two = [slot(Some(t(130))), slot(None)];
        assert_eq!(backlog(t(100), 4, &two), Duration::from_millis(30));
    }

    #[test]
    fn idle_edges_fill_first_up_to_max_batch_in_priority_order() {
        let p = profile(&[(1, 100.0), (4, 160.0)], 2);
        let engines = [
            EngineSlot {
                tier: Tier::Edge,
                max_batch: 2,
                busy_until: None,
                profile: &p,
                rtt: Duration::ZERO,
            },
            EngineSlot {
                tier: Tier::Edge,
                max_batch: 2,
                busy_until: Some(t(50)),
                profile: &p,
                rtt: Duration::ZERO,
            },
            EngineSlot {
                tier: Tier::Edge,
                max_batch: 2,
                busy_until: None,
                profile: &p,
                rtt: Duration::ZERO,
            },
        ];
        let placed = place(t(0), &[4, 2, 0, 1, 3], &engines);
        assert_eq!(placed.batches, vec![vec![4, 2], vec![], vec![0, 1]]);
        assert_eq!(placed.offloaded, 0);
    }

    /// One edge instance busy until `edge_free_ms` with max batch 2 and 100 ms batches; one cloud
    /// instance with `cloud_ms` latency per batch and `rtt_ms` round trip.
    fn edge_and_cloud<'a>(
        edge: &'a EngineProfile,
        cloud: &'a EngineProfile,
        edge_free_ms: u64,
        rtt_ms: u64,
    ) -> Vec<EngineSlot<'a>> {
        vec![
            EngineSlot {
                tier: Tier::Edge,
                max_batch: 2,
                busy_until: Some(t(edge_free_ms)),
                profile: edge,
                rtt: Duration::ZERO,
            },
            EngineSlot {
                tier: Tier::Cloud,
                max_batch: cloud.max_batch as usize,
                busy_until: None,
                profile: cloud,
                rtt: Duration::from_millis(rtt_ms),
            },
        ]
    }

    #[test]
    fn offload_only_when_cloud_latency_plus_rtt_beats_the_edge_queue_delay() {
        let edge = profile(&[(1, 100.0), (2, 100.0)], 2);
        let cloud = profile(&[(1, 50.0), (2, 50.0), (3, 50.0)], 3);
        // Edge free at 300 ms; requests 0,1 would start at 300, 2,3 at 400, 4,5 at 500.
        // Cloud costs 50 + 300 = 350 ms: only requests whose edge delay exceeds 350 go.
        let engines = edge_and_cloud(&edge, &cloud, 300, 300);
        let placed = place(t(0), &[0, 1, 2, 3, 4, 5], &engines);
        // (offloaded requests do not take edge slots, so 2, 3 and 4 all see the 400 ms group).
        assert_eq!(
            placed.batches[1],
            vec![2, 3, 4],
            "delays 400 > 350; 0 and 1 wait only 300"
        );
        assert_eq!(placed.offloaded, 3);
        // Equal is not better: at delay exactly 350 nothing moves.
        let engines = edge_and_cloud(&edge, &cloud, 350, 300);
        let placed = place(t(0), &[0, 1], &engines);
        assert!(placed.batches[1].is_empty());
        // A fast enough cloud takes the head of the queue too, up to its max batch.
        let engines = edge_and_cloud(&edge, &cloud, 300, 10);
        let placed = place(t(0), &[0, 1, 2, 3, 4], &engines);
        assert_eq!(placed.batches[1], vec![0, 1, 2]);
        assert_eq!(placed.offloaded, 3);
    }

    #[test]
    fn offloaded_requests_leave_the_edge_queue() {
        // Cloud cost 250: requests 0 and 1 would wait 200 on the edge (they stay); 2 and 3 would
        // wait 300 -> cloud. The cloud is then full (max batch 2), so 4 stays pending.
        let edge = profile(&[(1, 100.0), (2, 100.0)], 2);
        let cloud = profile(&[(1, 200.0), (2, 200.0)], 2);
        let engines = edge_and_cloud(&edge, &cloud, 200, 50);
        let placed = place(t(0), &[0, 1, 2, 3, 4], &engines);
        assert_eq!(placed.batches[1], vec![2, 3]);
        assert!(placed.batches[0].is_empty(), "a busy edge gets nothing");
    }

    #[test]
    fn the_nearest_idle_edge_fills_first_and_the_far_one_takes_the_rest() {
        let p = profile(&[(1, 10.0), (2, 12.0)], 2);
        let edge = |rtt_ms: u64| EngineSlot {
            tier: Tier::Edge,
            max_batch: 2,
            busy_until: None,
            profile: &p,
            rtt: Duration::from_millis(rtt_ms),
        };
        // The far worker registered first (lower id) but the near one takes the head.
        let engines = [edge(40), edge(1)];
        let placed = place(t(0), &[3, 1], &engines);
        assert_eq!(placed.batches, vec![vec![], vec![3, 1]]);
        let placed = place(t(0), &[3, 1, 0, 2, 4], &engines);
        assert_eq!(placed.batches, vec![vec![0, 2], vec![3, 1]]);
        // Equal round trips keep `EngineId` order.
        let engines = [edge(5), edge(5)];
        let placed = place(t(0), &[3, 1, 0], &engines);
        assert_eq!(placed.batches, vec![vec![3, 1], vec![0]]);
    }

    #[test]
    fn without_edge_instances_everything_that_fits_goes_to_the_cloud() {
        let cloud = profile(&[(1, 500.0)], 2);
        let engines = [EngineSlot {
            tier: Tier::Cloud,
            max_batch: 2,
            busy_until: None,
            profile: &cloud,
            rtt: Duration::from_millis(100),
        }];
        let placed = place(t(0), &[2, 1, 0], &engines);
        assert_eq!(placed.batches[0], vec![2, 1]);
    }
}
