//! The process-wide wasmtime engines and the epoch ticker that enforces call deadlines.
//!
//! One [`Engine`] per process (per fuel setting): compiled code, the code cache key and the
//! epoch counter all belong to it. A ticker thread advances the epoch every [`EPOCH_TICK`];
//! each call sets `Store::set_epoch_deadline` so guest code traps once its deadline has
//! passed, wherever it is looping. The ticker starts with the first engine and runs for the
//! life of the process (one wake-up per millisecond).

use std::sync::Mutex;
use std::time::Duration;

use wasmtime::{Config, Engine};

/// How often the epoch advances: the granularity of call deadlines.
pub const EPOCH_TICK: Duration = Duration::from_millis(1);

/// The engines created so far: `[plain, fueled]`. Behind a lock so that two threads asking
/// at once cannot create (and tick) two engines for one slot.
static ENGINES: Mutex<[Option<Engine>; 2]> = Mutex::new([None, None]);

/// The shared engine: epoch interruption always on; fuel metering when `fuel` is true
/// (metering changes the generated code, so metered plugins live in their own engine).
pub fn shared(fuel: bool) -> Result<Engine, wasmtime::Error> {
    let mut engines = ENGINES
        .lock()
        .map_err(|_| wasmtime::Error::msg("plugin engine registry poisoned"))?;
    let slot = usize::from(fuel);
    if let Some(engine) = &engines[slot] {
        return Ok(engine.clone());
    }
    let engine = Engine::new(&config(fuel))?;
    if engines.iter().all(Option::is_none) {
        // Without the ticker deadlines would never fire: no engine without it.
        start_ticker()
            .map_err(|e| wasmtime::Error::msg(format!("cannot start the epoch ticker: {e}")))?;
    }
    engines[slot] = Some(engine.clone());
    Ok(engine)
}

fn config(fuel: bool) -> Config {
    let mut config = Config::new();
    config.wasm_component_model(true);
    config.epoch_interruption(true);
    config.consume_fuel(fuel);
    config.cranelift_opt_level(wasmtime::OptLevel::Speed);
    config
}

/// Ticks to pass to `Store::set_epoch_deadline` so a call is interrupted no earlier than
/// `deadline`: the current tick may be about to end, hence one tick more than the quotient.
pub fn deadline_ticks(deadline: Duration) -> u64 {
    let tick = EPOCH_TICK.as_nanos().max(1);
    let ticks = deadline.as_nanos().div_ceil(tick);
    u64::try_from(ticks)
        .unwrap_or(u64::MAX - 1)
        .saturating_add(1)
}

fn start_ticker() -> std::io::Result<()> {
    std::thread::Builder::new()
        .name("kairos-plugin-epoch".into())
        .spawn(|| {
            loop {
                std::thread::sleep(EPOCH_TICK);
                if let Ok(engines) = ENGINES.lock() {
                    for engine in engines.iter().flatten() {
                        engine.increment_epoch();
                    }
                }
            }
        })
        .map(drop)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadline_ticks_never_cut_a_call_short() {
        assert_eq!(deadline_ticks(Duration::ZERO), 1);
        assert_eq!(deadline_ticks(Duration::from_micros(1)), 2);
        assert_eq!(deadline_ticks(Duration::from_millis(5)), 6);
        assert_eq!(deadline_ticks(Duration::from_micros(5_500)), 7);
        assert_eq!(deadline_ticks(Duration::MAX), u64::MAX);
    }
}
