//! Batches of training examples as Burn tensors, and a loader that makes them on other threads
//! while training runs.
//!
//! A batch is collated on the host into planar `[batch, channels, height, width]` arrays in the
//! generator's value ranges (photo and relit sRGB mapped to `[-1, 1]`, albedo in `[0, 1]`,
//! camera-space normals, linear HDR shading) and moved to the training device in one copy per
//! layer. Batch `i` is a pure function of `i` (see [`BatchLoader`]), so a resumed run sees the
//! same data as an uninterrupted one.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use burn::tensor::{Device, Tensor, TensorData};
use volux_envmap::LightMapSet;
use volux_model::light_lookup::{Lighting, LightingTensorError, lighting_tensors};
use volux_model::pose::Pose;

use crate::layers::Layers;
use crate::training_sample::{LightingDraw, TrainingSample};

/// One batch on the host, planar `[batch, channels, h, w]` arrays.
#[derive(Clone, Debug, PartialEq)]
pub struct Batch {
    pub size: usize,
    /// Output (high) resolution.
    pub side: usize,
    /// Volume (low) resolution.
    pub side_lo: usize,
    /// Which batch of the stream this is.
    pub index: u64,
    /// Every layer, planar (`[batch, channels, side, side]`), sRGB layers mapped to
    /// `[-1, 1]`; empty where the dataset does not provide the layer.
    pub layers: Layers<Vec<f32>>,
    pub poses: Vec<Pose>,
    /// The (environment, rotation) each example was lit with; the generator's samples of this
    /// step are lit with the same draws.
    pub draws: Vec<LightingDraw>,
}

/// A batch on a device: every layer `[b, channels, side, side]` in the batch's ranges (see
/// [`crate::layers`]: sRGB layers in `[-1, 1]`, D_P's reals the photo); `None` where the
/// dataset does not provide the layer.
pub type BatchTensors = Layers<Option<Tensor<4>>>;

/// Appends a row-major layer of `channels`-vectors (interleaved) as `channels` planes, mapped
/// by `f`.
fn push_planar(out: &mut Vec<f32>, layer: &[f32], channels: usize, f: impl Fn(f32) -> f32) {
    for c in 0..channels {
        out.extend(layer.iter().skip(c).step_by(channels).map(|&v| f(v)));
    }
}

impl Batch {
    /// Collates examples of equal sizes and layers (checked) into a batch.
    pub fn collate(index: u64, samples: &[TrainingSample]) -> Batch {
        let first = samples.first().expect("a batch has at least one example");
        let (side, factor) = (first.side, first.factor);
        assert!(
            samples.iter().all(|s| s.side == side
                && s.factor == factor
                && s.layers.map(|_, v| v.is_empty()) == first.layers.map(|_, v| v.is_empty())),
            "examples of one batch share their sizes and layers"
        );
        let layers = Layers::from_fn(|layer| {
            let mut planes = Vec::with_capacity(samples.len() * layer.floats(side, factor));
            let map: fn(f32) -> f32 = if layer.is_srgb() {
                |v| v * 2.0 - 1.0
            } else {
                |v| v
            };
            for s in samples {
                push_planar(&mut planes, s.layers.get(layer), layer.channels(), map);
            }
            planes
        });
        Batch {
            size: samples.len(),
            side,
            side_lo: side / factor,
            index,
            layers,
            poses: samples.iter().map(|s| s.pose).collect(),
            draws: samples.iter().map(|s| s.draw).collect(),
        }
    }

    /// The light maps and yaws the batch's draws name, on `device`, as the generator's
    /// `Lighting` (one map per example for each exponent of the bank's sets).
    pub fn lighting(
        &self,
        bank: &[LightMapSet],
        device: &Device,
    ) -> Result<Lighting, LightingTensorError> {
        let sets: Vec<&LightMapSet> = self
            .draws
            .iter()
            .map(|d| {
                bank.get(d.map)
                    .ok_or(LightingTensorError::Index(d.map, bank.len()))
            })
            .collect::<Result<_, _>>()?;
        let yaws: Vec<f64> = self.draws.iter().map(|d| d.yaw).collect();
        lighting_tensors(&sets, &yaws, device)
    }

    /// Which layers the batch has.
    pub fn provided(&self) -> Layers<bool> {
        self.layers.map(|_, v| !v.is_empty())
    }

    /// The batch on `device`.
    pub fn to_tensors(&self, device: &Device) -> BatchTensors {
        let factor = self.side / self.side_lo;
        self.layers.map(|layer, values| {
            let s = layer.side(self.side, factor);
            let shape = [self.size, layer.channels(), s, s];
            (!values.is_empty())
                .then(|| Tensor::<4>::from_data(TensorData::new(values.clone(), shape), device))
        })
    }
}

/// Makes batches `start, start + 1, ...` on a background thread, `prefetch` ahead of the
/// consumer; the first error ends the stream (and is returned by [`BatchLoader::next`]).
/// Dropping the loader stops the thread.
pub struct BatchLoader<E> {
    receiver: Option<Receiver<Result<Batch, E>>>,
    worker: Option<JoinHandle<()>>,
}

impl<E: Send + 'static> BatchLoader<E> {
    /// `make(i)` builds batch `i`; it should be a pure function of `i`. It runs in a rayon pool
    /// of one thread of its own, so its parallel loops leave the global pool to the consumer.
    pub fn spawn(
        start: u64,
        prefetch: usize,
        make: impl Fn(u64) -> Result<Batch, E> + Send + 'static,
    ) -> BatchLoader<E> {
        let (sender, receiver): (SyncSender<Result<Batch, E>>, _) = sync_channel(prefetch.max(1));
        let worker = std::thread::Builder::new()
            .name("volux-batches".into())
            .spawn(move || {
                let run = move || {
                    for i in start.. {
                        let batch = make(i);
                        let failed = batch.is_err();
                        if sender.send(batch).is_err() || failed {
                            return;
                        }
                    }
                };
                // A pool of its own with one thread: the batches' parallel loops (rendering,
                // look-ups) then never queue work on the global pool whose threads run the
                // training step's kernels, which would otherwise wait behind them.
                match rayon::ThreadPoolBuilder::new()
                    .num_threads(1)
                    .thread_name(|_| "volux-batches-pool".into())
                    .start_handler(|_| yield_to_the_step())
                    .build()
                {
                    Ok(pool) => pool.install(run),
                    Err(_) => run(),
                }
            })
            .expect("spawning the batch thread");
        BatchLoader {
            receiver: Some(receiver),
            worker: Some(worker),
        }
    }

    /// The next batch, waiting for it if it is not ready; `None` after an error was returned.
    pub fn next_batch(&mut self) -> Option<Result<Batch, E>> {
        self.receiver.as_ref()?.recv().ok()
    }
}

/// Lowers the calling thread's scheduling priority by [`LOADER_NICENESS`] steps (Linux:
/// niceness is per thread): on a machine whose cores all run the training step's kernels, the
/// batches are then made mostly in the step's idle moments (its serial sections, its waits)
/// instead of taking a core's share from it, and the prefetched batches keep the step fed.
fn yield_to_the_step() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid, getpriority and setpriority have no memory-safety preconditions; on
        // Linux a thread id names that thread alone.
        let ok = unsafe {
            let tid = libc::gettid() as libc::id_t;
            let current = libc::getpriority(libc::PRIO_PROCESS, tid);
            let lower = (current + LOADER_NICENESS).min(19);
            libc::setpriority(libc::PRIO_PROCESS, tid, lower) == 0
        };
        if !ok {
            tracing::debug!("could not lower the batch thread's priority; it keeps its own");
        }
    }
}

/// How much lower the batch thread's priority is than the process's (niceness steps; 19 is
/// the lowest priority there is).
const LOADER_NICENESS: i32 = 10;

impl<E> Drop for BatchLoader<E> {
    fn drop(&mut self) {
        // Closing the channel makes the worker's next send fail, which ends it.
        self.receiver.take();
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layers::Layer;

    fn sample(side: usize, value: f32) -> TrainingSample {
        let n = side * side;
        let lo = n / 4;
        TrainingSample {
            side,
            factor: 2,
            pose: Pose::new(value as f64, 0.0),
            draw: LightingDraw { map: 1, yaw: 0.5 },
            layers: Layers {
                photo: [value, 0.0, 1.0].repeat(n),
                relit: vec![0.5; 3 * n],
                albedo_hi: (0..n).flat_map(|i| [i as f32, value, 0.0]).collect(),
                albedo_lo: vec![value; 3 * lo],
                normals_lo: [0.0, 0.0, value].repeat(lo),
                mask: vec![value; n],
                diffuse: vec![2.0; 3 * n],
                specular: vec![3.0; 3 * n],
            },
        }
    }

    #[test]
    fn batches_are_made_outside_the_global_rayon_pool_at_a_lower_priority() {
        #[cfg(target_os = "linux")]
        let spawner = niceness();
        let mut loader = BatchLoader::<String>::spawn(0, 1, move |i| {
            // Inside the loader's own pool: one thread, not the global pool's.
            assert_eq!(rayon::current_num_threads(), 1);
            assert!(rayon::current_thread_index().is_some());
            #[cfg(target_os = "linux")]
            assert_eq!(niceness(), (spawner + LOADER_NICENESS).min(19));
            Ok(Batch::collate(i, &[sample(4, i as f32), sample(4, 1.0)]))
        });
        for _ in 0..2 {
            loader.next_batch().expect("a batch").expect("made");
        }
    }

    /// The calling thread's niceness.
    #[cfg(target_os = "linux")]
    fn niceness() -> i32 {
        // SAFETY: no memory-safety preconditions.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
    }

    #[test]
    fn collation_is_planar_and_in_the_generators_ranges() {
        let batch = Batch::collate(7, &[sample(4, 0.25), sample(4, 1.0)]);
        let t = batch
            .to_tensors(&Device::flex())
            .map(|_, t| t.clone().unwrap());
        assert_eq!(t.photo.dims(), [2, 3, 4, 4]);
        assert_eq!(t.albedo_lo.dims(), [2, 3, 2, 2]);
        assert_eq!(t.mask.dims(), [2, 1, 4, 4]);
        let photo = volux_model::backend::to_f32_vec(t.photo);
        // Example 0, red plane: 0.25 -> -0.5; green plane 0 -> -1; blue 1 -> 1.
        assert_eq!(&photo[..16], &[-0.5; 16]);
        assert_eq!(&photo[16..32], &[-1.0; 16]);
        assert_eq!(&photo[32..48], &[1.0; 16]);
        assert_eq!(photo[48], 1.0);
        let albedo = volux_model::backend::to_f32_vec(t.albedo_hi);
        // Red plane of example 1 holds the pixel index, row-major.
        assert_eq!(&albedo[48..52], &[0.0, 1.0, 2.0, 3.0]);
        assert_eq!(
            (batch.index, batch.poses[1], batch.draws[0].map),
            (7, Pose::new(1.0, 0.0), 1)
        );
    }

    #[test]
    fn layers_a_dataset_does_not_provide_stay_off_the_device() {
        let photos_only = |value| {
            let mut s = sample(4, value);
            let photo = std::mem::take(&mut s.layers.photo);
            s.layers = Layers {
                photo,
                ..Layers::default()
            };
            s
        };
        let batch = Batch::collate(0, &[photos_only(0.5), photos_only(1.0)]);
        assert_eq!(batch.provided(), Layers::from_fn(|l| l == Layer::Photo));
        let t = batch.to_tensors(&Device::flex());
        assert_eq!(t.photo.as_ref().map(|p| p.dims()), Some([2, 3, 4, 4]));
        assert!(t.iter().all(|(l, t)| t.is_some() == (l == Layer::Photo)));
    }

    #[test]
    #[should_panic(expected = "share their sizes and layers")]
    fn a_batch_of_mixed_layers_is_refused() {
        let mut partial = sample(4, 0.5);
        partial.layers.relit.clear();
        Batch::collate(0, &[sample(4, 0.5), partial]);
    }

    #[test]
    fn the_loader_streams_batches_in_order_and_stops_at_an_error() {
        let mut loader = BatchLoader::spawn(3, 2, |i| {
            if i == 6 {
                Err(format!("batch {i} failed"))
            } else {
                Ok(Batch::collate(i, &[sample(2, i as f32)]))
            }
        });
        let indices: Vec<u64> = (0..3)
            .map(|_| loader.next_batch().unwrap().unwrap().index)
            .collect();
        assert_eq!(indices, [3, 4, 5]);
        assert_eq!(loader.next_batch().unwrap().unwrap_err(), "batch 6 failed");
        assert!(loader.next_batch().is_none());
        // Dropping a loader that is still producing ends its thread.
        let mut endless = BatchLoader::spawn(0, 1, |i| {
            Ok::<_, String>(Batch::collate(i, &[sample(2, 0.0)]))
        });
        assert_eq!(endless.next_batch().unwrap().unwrap().index, 0);
        drop(endless);
    }
}
