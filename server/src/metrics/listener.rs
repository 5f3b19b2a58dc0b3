//! Which connections the metrics listener holds, and which one gives way when it is full.
//!
//! Every accepted connection gets a [`Slot`] at once; nothing waits for a place. A connection
//! that has not yet sent its whole request head is *idle* and may be evicted; one whose head has
//! arrived is being answered (a few milliseconds) and is never evicted. When a new connection
//! would exceed [`Limits::per_address`] connections from its address, that address's oldest idle
//! connection is evicted; when it would exceed [`Limits::total`], the oldest idle connection
//! of any address is. Only if every held connection is being answered is the new one refused.
//!
//! So silent clients cannot keep a probe out: a new connection always displaces the oldest silent
//! one, and one address's silent connections displace only each other. Kubelet's probe and
//! Prometheus's scrape send their request as soon as they connect, and are answered before a
//! flood of new connections could reach them in the eviction order.

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex, PoisonError};

use tokio::sync::oneshot;

/// How many connections the table holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Limits {
    /// All addresses together.
    pub(super) total: usize,
    /// From one address.
    pub(super) per_address: usize,
}

#[derive(Debug)]
struct Entry {
    address: IpAddr,
    /// Dropped to evict the connection; `None` once its head has arrived.
    evict: Option<oneshot::Sender<()>>,
}

#[derive(Debug, Default)]
struct State {
    next: u64,
    /// By admission order: the first idle entry is the oldest.
    entries: BTreeMap<u64, Entry>,
}

/// The connections held now. Shared by the accept loop and the connection tasks.
#[derive(Debug)]
pub(super) struct Table {
    limits: Limits,
    state: Mutex<State>,
}

/// What [`Table::admit`] decided.
#[derive(Debug)]
pub(super) struct Admitted {
    /// The new connection's place; `None`: refused, every held connection is being answered.
    pub(super) slot: Option<Slot>,
    /// Idle connections evicted to make room (0 or 1).
    pub(super) evicted: usize,
}

/// A held connection's place; dropping it frees the place.
#[derive(Debug)]
pub(super) struct Slot {
    id: u64,
    table: Arc<Table>,
    /// Resolves (with an error) when the connection is evicted.
    evicted: Option<oneshot::Receiver<()>>,
}

impl Table {
    /// An empty table; limits below 1 count as 1.
    pub(super) fn new(limits: Limits) -> Arc<Table> {
        Arc::new(Table {
            limits: Limits {
                total: limits.total.max(1),
                per_address: limits.per_address.clamp(1, limits.total.max(1)),
            },
            state: Mutex::new(State::default()),
        })
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A place for a connection from `address`, evicting the oldest idle connection first if
    /// the table is full for that address or in total.
    pub(super) fn admit(self: &Arc<Self>, address: IpAddr) -> Admitted {
        let mut state = self.state();
        let mut evicted = 0;
        let from_address = state
            .entries
            .values()
            .filter(|e| e.address == address)
            .count();
        if from_address >= self.limits.per_address {
            if !evict_oldest_idle(&mut state, Some(address)) {
                return Admitted {
                    slot: None,
                    evicted,
                };
            }
            evicted += 1;
        }
        if state.entries.len() >= self.limits.total {
            if !evict_oldest_idle(&mut state, None) {
                return Admitted {
                    slot: None,
                    evicted,
                };
            }
            evicted += 1;
        }
        let id = state.next;
        state.next += 1;
        let (evict, evicted_rx) = oneshot::channel();
        state.entries.insert(
            id,
            Entry {
                address,
                evict: Some(evict),
            },
        );
        Admitted {
            slot: Some(Slot {
                id,
                table: self.clone(),
                evicted: Some(evicted_rx),
            }),
            evicted,
        }
    }

    /// Connections held now.
    #[cfg(test)]
    pub(super) fn len(&self) -> usize {
        self.state().entries.len()
    }
}

/// Evicts the oldest idle entry (of `address`, if given); `false` if there is none.
fn evict_oldest_idle(state: &mut State, address: Option<IpAddr>) -> bool {
    let oldest = state
        .entries
        .iter()
        .find(|(_, e)| e.evict.is_some() && address.is_none_or(|a| a == e.address))
        .map(|(&id, _)| id);
    match oldest {
        // Dropping the entry drops its sender, which wakes the connection's task.
        Some(id) => state.entries.remove(&id).is_some(),
        None => false,
    }
}

impl Slot {
    /// Resolves when the connection is evicted (never, once [`Slot::answering`] was called).
    pub(super) async fn evicted(&mut self) {
        match self.evicted.as_mut() {
            Some(rx) => {
                let _ = rx.await;
            }
            None => std::future::pending().await,
        }
    }

    /// The request head has arrived: from now on the connection is not evicted.
    pub(super) fn answering(&mut self) {
        self.evicted = None;
        if let Some(entry) = self.table.state().entries.get_mut(&self.id) {
            entry.evict = None;
        }
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.table.state().entries.remove(&self.id);
    }
}

#[cfg(test)]
mod tests {
    use std::net::Ipv4Addr;

    use super::*;

    fn ip(last: u8) -> IpAddr {
        IpAddr::V4(Ipv4Addr::new(10, 0, 0, last))
    }

    fn evicted_now(slot: &mut Slot) -> bool {
        let rx = slot.evicted.as_mut().expect("idle");
        matches!(rx.try_recv(), Err(oneshot::error::TryRecvError::Closed))
    }

    #[test]
    fn a_full_address_evicts_its_own_oldest_idle_connection() {
        let table = Table::new(Limits {
            total: 10,
            per_address: 2,
        });
        let mut a1 = table.admit(ip(1)).slot.unwrap();
        let mut a2 = table.admit(ip(1)).slot.unwrap();
        let mut b1 = table.admit(ip(2)).slot.unwrap();
        let third = table.admit(ip(1));
        assert_eq!(third.evicted, 1);
        assert!(evicted_now(&mut a1), "the oldest of that address");
        assert!(!evicted_now(&mut a2));
        assert!(!evicted_now(&mut b1), "another address is untouched");
        assert_eq!(table.len(), 3);
    }

    #[test]
    fn a_full_table_evicts_the_oldest_idle_connection_and_never_one_being_answered() {
        let table = Table::new(Limits {
            total: 2,
            per_address: 2,
        });
        let mut first = table.admit(ip(1)).slot.unwrap();
        first.answering();
        let mut second = table.admit(ip(2)).slot.unwrap();
        let third = table.admit(ip(3));
        assert_eq!(third.evicted, 1);
        assert!(evicted_now(&mut second), "the oldest idle one");
        let mut third = third.slot.unwrap();
        third.answering();
        // Both held connections are being answered: the next one is refused.
        let refused = table.admit(ip(4));
        assert!(refused.slot.is_none());
        assert_eq!(refused.evicted, 0);
        drop(first);
        assert!(table.admit(ip(4)).slot.is_some(), "a freed place is taken");
    }
}
