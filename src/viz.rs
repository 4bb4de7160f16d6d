//! Rerun logging: one recording stream fed from its own thread through a
//! bounded channel, so that logging never blocks the processing path (a frame
//! the logger cannot take is dropped and counted).
//!
//! Entities: `camera/depth/raw`, `camera/depth/recovered` (depth images, mm),
//! `camera/translucent_mask`, `points/raw` (the translucent pixels' readings,
//! red), `points/recovered` (their recovered depth, cyan), `points/scene`
//! (the rest, grey), `translucency/xi`, `translucency/xi_lower`,
//! `translucency/xi_upper`, `translucency/pixels`; timelines `stamp` (the
//! header stamp) and `frame`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, SyncSender};
use std::sync::Arc;

use crate::outputs::points_m;
use crate::physics::ImageBuf;
use nalgebra::Vector3;

/// Where Rerun data goes (parameter / flag `rerun`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RerunTarget {
    /// No logging.
    Off,
    /// A `.rrd` file.
    File(PathBuf),
    /// A viewer's gRPC address (`rerun+http://HOST:PORT/proxy`, or `HOST:PORT`).
    Viewer(String),
}

impl RerunTarget {
    /// `off` (or empty), a path ending in `.rrd`, or a viewer address.
    pub fn parse(s: &str) -> Result<Self, String> {
        let s = s.trim();
        if s.is_empty() || s.eq_ignore_ascii_case("off") || s == "false" {
            return Ok(RerunTarget::Off);
        }
        if s.ends_with(".rrd") {
            return Ok(RerunTarget::File(PathBuf::from(s)));
        }
        if s.starts_with("rerun+http://") || s.starts_with("rerun+https://") {
            return Ok(RerunTarget::Viewer(s.to_string()));
        }
        let host_port = s
            .rsplit_once(':')
            .is_some_and(|(h, p)| !h.is_empty() && p.parse::<u16>().is_ok());
        if host_port {
            return Ok(RerunTarget::Viewer(format!("rerun+http://{s}/proxy")));
        }
        Err(format!(
            "rerun {s:?}: expected off, a path ending in .rrd, or a viewer address (HOST:PORT or rerun+http://HOST:PORT/proxy)"
        ))
    }
}

/// One frame's worth of what is logged.
#[derive(Debug, Clone)]
pub struct FrameViz {
    /// Header stamp, ns.
    pub stamp_ns: u64,
    /// Frame counter.
    pub frame: u64,
    /// The camera's unit rays.
    pub rays: Arc<ImageBuf<Vector3<f64>>>,
    /// Reading, z mm.
    pub raw_z_mm: ImageBuf<f32>,
    /// Corrected, z mm.
    pub recovered_z_mm: ImageBuf<f32>,
    /// Translucent pixels.
    pub mask: ImageBuf<bool>,
    /// ξ and its interval, when known.
    pub xi: Option<(f64, [f64; 2])>,
    /// The frame's objects, each logged as an entity `objects/<id>` over time.
    pub objects: Vec<ObjectViz>,
}

/// One object of a frame as logged: its ξ, interval and class.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectViz {
    /// The object's id (stable while it is followed).
    pub id: u32,
    /// Its ξ and interval.
    pub xi: (f64, [f64; 2]),
    /// Published opaque (readings kept).
    pub opaque: bool,
    /// Its pixels in this frame.
    pub pixels: usize,
    /// With a materials file: its class (a known material's name, `opaque` or `unknown`)
    /// and the class's probability.
    pub class: Option<(String, f64)>,
}

impl FrameViz {
    /// The objects of a frame's regions (those of an object), as [`FrameViz::objects`] holds them.
    pub fn objects_of(regions: &[crate::pipeline::RegionOutput]) -> Vec<ObjectViz> {
        regions
            .iter()
            .filter(|r| r.id != 0)
            .map(|r| ObjectViz {
                id: r.id,
                xi: (r.xi.xi, r.xi.interval),
                opaque: r.opaque,
                pixels: r.pixels,
                class: r.class.as_ref().map(|c| (c.name.clone(), c.probability)),
            })
            .collect()
    }
}

/// A running logger. Dropping it (or [`VizSink::finish`]) flushes the recording.
pub struct VizSink {
    tx: Option<SyncSender<FrameViz>>,
    dropped: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<Result<u64, String>>>,
}

impl VizSink {
    /// Starts logging to `target` (None for [`RerunTarget::Off`]). The queue
    /// holds `queue` frames; more are dropped while the logger is busy.
    pub fn start(target: &RerunTarget, app_id: &'static str, queue: usize) -> Result<Option<Self>, String> {
        if *target == RerunTarget::Off {
            return Ok(None);
        }
        let rec = backend::open(target, app_id)?;
        let (tx, rx) = sync_channel::<FrameViz>(queue.max(1));
        let thread = std::thread::Builder::new()
            .name("rerun".into())
            .spawn(move || {
                let mut n = 0;
                for f in rx {
                    backend::log_frame(&rec, &f)?;
                    n += 1;
                }
                backend::close(rec)?;
                Ok(n)
            })
            .map_err(|e| format!("starting the Rerun thread: {e}"))?;
        Ok(Some(Self {
            tx: Some(tx),
            dropped: Arc::new(AtomicU64::new(0)),
            thread: Some(thread),
        }))
    }

    /// Queues a frame without waiting; returns false (and counts it) when the logger is behind.
    pub fn log(&self, f: FrameViz) -> bool {
        let sent = self.tx.as_ref().is_some_and(|tx| tx.try_send(f).is_ok());
        if !sent {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        sent
    }

    /// Frames the logger could not take.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Logs what is queued, closes the recording; returns the frames logged.
    pub fn finish(mut self) -> Result<u64, String> {
        self.tx.take();
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err("the Rerun thread panicked".into()),
            None => Ok(0),
        }
    }
}

impl Drop for VizSink {
    fn drop(&mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A recording written in the caller's thread, every frame kept (offline
/// use, e.g. `replay --rerun`; the node uses [`VizSink`], which never waits).
pub struct Recorder {
    rec: backend::Stream,
}

impl Recorder {
    /// Opens `target` (not [`RerunTarget::Off`]).
    pub fn open(target: &RerunTarget, app_id: &'static str) -> Result<Self, String> {
        Ok(Self {
            rec: backend::open(target, app_id)?,
        })
    }

    /// Logs one frame.
    pub fn log(&self, f: &FrameViz) -> Result<(), String> {
        backend::log_frame(&self.rec, f)
    }

    /// Flushes and closes the recording.
    pub fn finish(self) -> Result<(), String> {
        backend::close(self.rec)
    }
}

/// A curve in a 2D plot (e.g. mean residual against a physical quantity).
#[derive(Debug, Clone)]
pub struct Curve {
    /// Rerun entity path, e.g. `audit/residual_vs_phase/before`.
    pub entity: String,
    /// `(x, y)` points in drawing order.
    pub points: Vec<[f32; 2]>,
    /// RGB colour.
    pub color: [u8; 3],
}

/// Writes curves as line strips with their points to a Rerun target (the
/// audit's plots, viewable beside its SVG files).
pub fn write_curves(target: &RerunTarget, app_id: &'static str, curves: &[Curve]) -> Result<(), String> {
    let rec = backend::open(target, app_id)?;
    backend::log_curves(&rec, curves)?;
    backend::close(rec)
}

/// The translucent pixels' points (raw, recovered) and the rest of the scene.
pub fn split_clouds(f: &FrameViz) -> [Vec<[f32; 3]>; 3] {
    let raw = points_m(&f.rays, &f.raw_z_mm);
    let rec = points_m(&f.rays, &f.recovered_z_mm);
    let (mut r, mut c, mut s) = (vec![], vec![], vec![]);
    for i in 0..f.mask.len().min(raw.len()).min(rec.len()) {
        let ok = |p: &[f32; 3]| p.iter().all(|v| v.is_finite());
        if f.mask.data[i] {
            if ok(&raw.data[i]) {
                r.push(raw.data[i]);
            }
            if ok(&rec.data[i]) {
                c.push(rec.data[i]);
            }
        } else if ok(&rec.data[i]) {
            s.push(rec.data[i]);
        }
    }
    [r, c, s]
}

#[cfg(feature = "rerun")]
mod backend {
    use super::{split_clouds, FrameViz, RerunTarget};
    use rerun::{ChannelDatatype, Color, DepthImage, Points3D, RecordingStream, RecordingStreamBuilder, Scalars};

    pub type Stream = RecordingStream;

    pub fn open(target: &RerunTarget, app_id: &'static str) -> Result<RecordingStream, String> {
        let b = RecordingStreamBuilder::new(app_id);
        match target {
            RerunTarget::File(p) => b
                .save(p)
                .map_err(|e| format!("rerun: cannot write {}: {e}", p.display())),
            RerunTarget::Viewer(url) => b
                .connect_grpc_opts(url.clone())
                .map_err(|e| format!("rerun: cannot connect to {url}: {e}")),
            RerunTarget::Off => Err("rerun is off".into()),
        }
    }

    fn depth(z: &crate::physics::ImageBuf<f32>) -> DepthImage {
        let bytes: Vec<u8> = z.data.iter().flat_map(|v| v.to_le_bytes()).collect();
        DepthImage::from_data_type_and_bytes(bytes, [z.width as u32, z.height as u32], ChannelDatatype::F32)
            .with_meter(1000.0)
    }

    pub fn log_frame(rec: &RecordingStream, f: &FrameViz) -> Result<(), String> {
        let err = |e: rerun::RecordingStreamError| format!("rerun: {e}");
        rec.set_time_sequence("frame", f.frame as i64);
        rec.set_timestamp_nanos_since_epoch("stamp", f.stamp_ns as i64);
        rec.log("camera/depth/raw", &depth(&f.raw_z_mm)).map_err(err)?;
        rec.log("camera/depth/recovered", &depth(&f.recovered_z_mm))
            .map_err(err)?;
        let mask: Vec<u8> = f.mask.data.iter().map(|&m| u8::from(m) * 255).collect();
        rec.log(
            "camera/translucent_mask",
            &DepthImage::from_data_type_and_bytes(
                mask,
                [f.mask.width as u32, f.mask.height as u32],
                ChannelDatatype::U8,
            ),
        )
        .map_err(err)?;
        let [raw, recovered, scene] = split_clouds(f);
        rec.log(
            "points/raw",
            &Points3D::new(raw)
                .with_colors([Color::from_rgb(230, 40, 40)])
                .with_radii([0.003]),
        )
        .map_err(err)?;
        rec.log(
            "points/recovered",
            &Points3D::new(recovered)
                .with_colors([Color::from_rgb(0, 220, 230)])
                .with_radii([0.003]),
        )
        .map_err(err)?;
        rec.log(
            "points/scene",
            &Points3D::new(scene)
                .with_colors([Color::from_rgb(150, 150, 150)])
                .with_radii([0.002]),
        )
        .map_err(err)?;
        if let Some((xi, [lo, hi])) = f.xi {
            rec.log("translucency/xi", &Scalars::new([xi])).map_err(err)?;
            rec.log("translucency/xi_lower", &Scalars::new([lo])).map_err(err)?;
            rec.log("translucency/xi_upper", &Scalars::new([hi])).map_err(err)?;
        }
        let n = f.mask.data.iter().filter(|&&m| m).count();
        rec.log("translucency/pixels", &Scalars::new([n as f64])).map_err(err)?;
        for o in &f.objects {
            log_object(rec, o).map_err(err)?;
        }
        Ok(())
    }

    /// One object as the entity `objects/<id>`: ξ and its interval, pixels, opaque, class.
    fn log_object(rec: &RecordingStream, o: &super::ObjectViz) -> Result<(), rerun::RecordingStreamError> {
        let id = o.id;
        let (xi, [lo, hi]) = o.xi;
        rec.log(format!("objects/{id}/xi"), &Scalars::new([xi]))?;
        rec.log(format!("objects/{id}/xi_lower"), &Scalars::new([lo]))?;
        rec.log(format!("objects/{id}/xi_upper"), &Scalars::new([hi]))?;
        rec.log(format!("objects/{id}/pixels"), &Scalars::new([o.pixels as f64]))?;
        rec.log(
            format!("objects/{id}/opaque"),
            &Scalars::new([f64::from(u8::from(o.opaque))]),
        )?;
        if let Some((name, p)) = &o.class {
            rec.log(
                format!("objects/{id}/class"),
                &rerun::TextLog::new(format!("{name} (probability {p:.2})")),
            )?;
            rec.log(format!("objects/{id}/class_probability"), &Scalars::new([*p]))?;
        }
        Ok(())
    }

    pub fn log_curves(rec: &RecordingStream, curves: &[super::Curve]) -> Result<(), String> {
        for c in curves {
            let color = Color::from_rgb(c.color[0], c.color[1], c.color[2]);
            rec.log(
                c.entity.as_str(),
                &rerun::LineStrips2D::new([c.points.clone()]).with_colors([color]),
            )
            .map_err(|e| format!("rerun: {e}"))?;
            rec.log(
                format!("{}/points", c.entity),
                &rerun::Points2D::new(c.points.clone())
                    .with_colors([color])
                    .with_radii([2.0]),
            )
            .map_err(|e| format!("rerun: {e}"))?;
        }
        Ok(())
    }

    pub fn close(rec: RecordingStream) -> Result<(), String> {
        rec.flush_blocking().map_err(|e| format!("rerun: flushing: {e}"))
    }
}

#[cfg(not(feature = "rerun"))]
mod backend {
    use super::{FrameViz, RerunTarget};

    pub struct Never;

    pub type Stream = Never;

    pub fn open(_: &RerunTarget, _: &'static str) -> Result<Never, String> {
        Err("this build has no Rerun support (rebuild with the default `rerun` feature), so `rerun` must be off".into())
    }

    pub fn log_frame(_: &Never, _: &FrameViz) -> Result<(), String> {
        Ok(())
    }

    pub fn log_curves(_: &Never, _: &[super::Curve]) -> Result<(), String> {
        Ok(())
    }

    pub fn close(_: Never) -> Result<(), String> {
        Ok(())
    }
}
