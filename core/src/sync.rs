//! One way to take a lock: [`lock`] ignores poisoning.
//!
//! Every mutex Kairos shares between threads guards data that stays consistent at every await
//! and every early return (counters, maps of handles, a pool, a published report): a panic on
//! another thread while it held the lock leaves nothing half-written that a later reader could
//! misread. Treating the poison as fatal would instead turn one panicked task into a failure of
//! every later decision, so the guard is taken as it is.

use std::sync::{Mutex, MutexGuard, PoisonError};

/// Locks `mutex`, taking its data as it is if a panic poisoned it (see the module docs).
pub fn lock<T: ?Sized>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_poisoned_mutex_is_still_locked_with_its_data() {
        let mutex = std::sync::Arc::new(Mutex::new(7));
        let poisoner = mutex.clone();
        let _ = std::thread::spawn(move || {
            let _guard = poisoner.lock().unwrap_or_else(PoisonError::into_inner);
            panic!("poison the mutex");
        })
        .join();
        assert!(mutex.is_poisoned());
        assert_eq!(*lock(&mutex), 7);
    }
}
