//! Named timing spans for per-phase profiling of the code that trains.
//!
//! The generator and the training step open a [`span`] around each phase (mapping network,
//! field, compositing, ...). Spans do nothing unless a [`Profiler`] is running on the calling
//! thread: then each span boundary synchronises the device (so that a backend that queues
//! work, such as wgpu, is timed on finished work; Burn's flex CPU backend runs every op eagerly
//! and its sync is free) and the span's *exclusive* time (minus the spans nested inside it) is
//! added to its phase. A disabled span is one thread-local flag read: no sync, no allocation,
//! no clock.
//!
//! ```ignore
//! let profiler = Profiler::start(&device);
//! train_step(...);                     // spans inside record their times
//! let times = profiler.take();         // [(phase, seconds, calls)] since start / last take
//! ```

use std::cell::{Cell, RefCell};
use std::marker::PhantomData;
use std::time::{Duration, Instant};

use burn::tensor::Device;

/// A phase of a training step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// `z -> w`.
    Mapping,
    /// The NeIIF at every composited sample (both passes), the normals' reverse sweep included.
    Field,
    /// The density-only passes that place the importance samples (`crate::proposal`).
    Proposal,
    /// Rays, sampling, compositing weights and accumulation, light-map look-ups, images.
    Compositing,
    /// The upsampler (`A_hi`, `F_hi`).
    Upsampler,
    /// Shading upsampling and the relighting U-Net (`I_relit`).
    Relighting,
    /// Every active discriminator's one pass on the fakes and its pullback (the generator
    /// loss's input gradient), the discriminators side by side on the CPU's threads.
    DiscriminatorsOnFakes,
    /// `backward()` of the generator's loss, from the pullbacks' input gradients down (when
    /// the step's parts run in turn).
    GeneratorBackward,
    /// The generator's backward pass and the discriminator phase side by side (on the CPU):
    /// [`Phase::GeneratorBackward`] and [`Phase::DiscriminatorStep`] at once.
    BackwardPasses,
    /// The generator's Adam step and its finiteness check.
    GeneratorUpdate,
    /// The discriminator phase: each discriminator's pass on the reals (with lazy R1 on its
    /// steps) and the backward through both its passes, the discriminators side by side on
    /// the CPU (when the step's parts run in turn).
    DiscriminatorStep,
    /// The discriminators' Adam step and its finiteness check.
    DiscriminatorUpdate,
    /// Lazy R1's extra time. No span records it: its work runs inside the discriminator step,
    /// and a benchmark takes it as that phase's time on a step with R1 less the median of the
    /// steps without.
    R1,
    /// The generator's moving average.
    Ema,
}

impl Phase {
    /// A short label for tables.
    pub fn label(self) -> &'static str {
        match self {
            Phase::Mapping => "mapping",
            Phase::Field => "NeIIF field + normals",
            Phase::Proposal => "density-only proposal",
            Phase::Compositing => "compositing + light look-ups",
            Phase::Upsampler => "upsampler",
            Phase::Relighting => "relighting net",
            Phase::DiscriminatorsOnFakes => "discriminators on fakes + pullbacks",
            Phase::GeneratorBackward => "generator backward",
            Phase::GeneratorUpdate => "generator Adam",
            Phase::BackwardPasses => "generator backward + discriminator step (side by side)",
            Phase::DiscriminatorStep => "discriminator step",
            Phase::DiscriminatorUpdate => "discriminator Adam",
            Phase::R1 => "R1 (extra on its step)",
            Phase::Ema => "EMA",
        }
    }
}

/// Time recorded for one phase.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhaseTime {
    pub phase: Phase,
    /// Exclusive wall time, summed over the phase's spans.
    pub seconds: f64,
    /// How many spans of the phase ended.
    pub calls: u32,
}

struct Recorder {
    device: Device,
    /// Open spans, innermost last, with the instant their exclusive time last resumed.
    stack: Vec<(Phase, Instant)>,
    totals: Vec<(Phase, Duration, u32)>,
}

impl Recorder {
    fn now(&self) -> Instant {
        // A failed sync shows up again in the next operation that reads back; the profile
        // only needs the queue drained.
        let _ = self.device.sync();
        Instant::now()
    }

    fn add(&mut self, phase: Phase, time: Duration, ended: bool) {
        let calls = u32::from(ended);
        match self.totals.iter_mut().find(|(p, ..)| *p == phase) {
            Some((_, t, n)) => {
                *t += time;
                *n += calls;
            }
            None => self.totals.push((phase, time, calls)),
        }
    }

    fn enter(&mut self, phase: Phase) {
        let now = self.now();
        if let Some(&(parent, since)) = self.stack.last() {
            self.add(parent, now - since, false);
        }
        self.stack.push((phase, now));
    }

    fn exit(&mut self) {
        let now = self.now();
        let (phase, since) = self.stack.pop().expect("a span is open");
        self.add(phase, now - since, true);
        if let Some(top) = self.stack.last_mut() {
            top.1 = now;
        }
    }
}

thread_local! {
    static ENABLED: Cell<bool> = const { Cell::new(false) };
    static RECORDER: RefCell<Option<Recorder>> = const { RefCell::new(None) };
}

/// An open span; its phase's time stops when it is dropped.
#[must_use = "a span measures until it is dropped"]
pub struct Span {
    active: bool,
    /// Spans belong to the thread that opened them.
    _thread: PhantomData<*const ()>,
}

impl Drop for Span {
    fn drop(&mut self) {
        if self.active {
            RECORDER.with_borrow_mut(|r| {
                if let Some(r) = r {
                    r.exit();
                }
            });
        }
    }
}

/// Opens a span of `phase` (a no-op unless a [`Profiler`] runs on this thread).
#[inline]
pub fn span(phase: Phase) -> Span {
    let active = ENABLED.get()
        && RECORDER.with_borrow_mut(|r| match r {
            Some(r) => {
                r.enter(phase);
                true
            }
            None => false,
        });
    Span {
        active,
        _thread: PhantomData,
    }
}

/// Runs `f` inside a span of `phase`.
#[inline]
pub fn timed<T>(phase: Phase, f: impl FnOnce() -> T) -> T {
    let _span = span(phase);
    f()
}

/// Whether a profiler runs on this thread.
pub fn enabled() -> bool {
    ENABLED.get()
}

/// Why a profiler cannot start.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("a profiler is already running on this thread")]
pub struct AlreadyRunning;

/// Records spans on the calling thread from [`Profiler::start`] until it is dropped.
pub struct Profiler {
    _thread: PhantomData<*const ()>,
}

impl Profiler {
    /// Starts recording, synchronising `device` at every span boundary.
    pub fn start(device: &Device) -> Result<Profiler, AlreadyRunning> {
        if ENABLED.get() {
            return Err(AlreadyRunning);
        }
        RECORDER.set(Some(Recorder {
            device: device.clone(),
            stack: Vec::new(),
            totals: Vec::new(),
        }));
        ENABLED.set(true);
        Ok(Profiler {
            _thread: PhantomData,
        })
    }

    /// The time of every phase since the start or the last `take`, in the order phases first
    /// ran; resets the totals. Open spans keep running.
    pub fn take(&self) -> Vec<PhaseTime> {
        RECORDER.with_borrow_mut(|r| {
            let r = r.as_mut().expect("the profiler is running");
            std::mem::take(&mut r.totals)
                .into_iter()
                .map(|(phase, t, calls)| PhaseTime {
                    phase,
                    seconds: t.as_secs_f64(),
                    calls,
                })
                .collect()
        })
    }
}

impl Drop for Profiler {
    fn drop(&mut self) {
        ENABLED.set(false);
        RECORDER.set(None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn busy(ms: u64) {
        let until = Instant::now() + Duration::from_millis(ms);
        while Instant::now() < until {
            std::hint::spin_loop();
        }
    }

    #[test]
    fn spans_record_nothing_without_a_profiler() {
        assert!(!enabled());
        let s = span(Phase::Mapping);
        assert!(!s.active);
        assert_eq!(timed(Phase::Field, || 7), 7);
    }

    #[test]
    fn nested_spans_record_exclusive_times_and_calls() {
        let p = Profiler::start(&Device::flex()).unwrap();
        assert_eq!(Profiler::start(&Device::flex()).err(), Some(AlreadyRunning));
        {
            let _outer = span(Phase::Compositing);
            busy(10);
            timed(Phase::Field, || busy(50));
            timed(Phase::Field, || busy(50));
            busy(10);
        }
        let t = p.take();
        assert_eq!(t.len(), 2, "{t:?}");
        let get = |phase| t.iter().find(|x| x.phase == phase).copied().unwrap();
        let (outer, inner) = (get(Phase::Compositing), get(Phase::Field));
        assert_eq!((outer.calls, inner.calls), (1, 2));
        // Exclusive: the outer span's own 20 ms, not the 120 ms it was open.
        assert!(outer.seconds >= 0.02, "{}", outer.seconds);
        assert!(inner.seconds >= 0.1, "{}", inner.seconds);
        assert!(outer.seconds < inner.seconds, "{t:?}");
        assert!(p.take().is_empty());
        drop(p);
        assert!(!enabled());
    }
}
