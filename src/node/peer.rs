//! The other side of the node on DDS: a ToF driver publishing depth, IR and
//! camera_info, a client of the two services, and a subscriber of the
//! outputs. Used by `demo`, the benchmarks and the tests.

use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::{anyhow, Result};
use ros2_client::{
    qos::{Durability, History},
    Client, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher, QosProfile, ServiceMapping, ServiceTypeName,
    Subscription,
};

use crate::msgs::translucent_tof::TranslucencyEstimate;
use crate::msgs::{CameraInfo, Header, Image, PointCloud2, TriggerRequest, TriggerResponse};

/// Resolves when the match `wait` waits for has happened, made anew every half second.
///
/// ros2-client's waits look at the match table when they are made, then only again when a
/// match event reaches them; those events go through a channel of 8 that drops what does
/// not fit. A burst of discovery (a node of 20 endpoints, a busy host) can drop the one
/// event a wait needs, and it then waits for ever. A wait made anew reads the table again.
pub async fn rearmed<F, Fut>(mut wait: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    while tokio::time::timeout(Duration::from_millis(500), wait()).await.is_err() {}
}

/// `img` with a new header stamp (same frame id).
pub fn restamp(img: &Image, stamp_ns: u64) -> Image {
    Image {
        header: Header::new(stamp_ns, img.header.frame_id.clone()),
        ..img.clone()
    }
}

/// A bag's camera_info (the first) and its depth + IR pairs by exact stamp,
/// as raw messages, for playing it to the node as a driver would.
pub fn bag_frames(path: &std::path::Path) -> Result<(CameraInfo, Vec<(Image, Image)>)> {
    use crate::bag::{select_topics, BagReader, TopicOverrides};
    let reader = BagReader::open(path).map_err(|e| anyhow!("opening {}: {e}", path.display()))?;
    let sel = select_topics(&reader.topics(), &TopicOverrides::default())?;
    let (mut depth, mut ir) = (BTreeMap::new(), BTreeMap::new());
    let mut info = None;
    for raw in reader.messages() {
        let raw = raw?;
        if raw.topic == sel.depth {
            let m: Image = BagReader::decode(&raw)?;
            depth.insert(m.header.stamp.as_log_time_ns(), m);
        } else if raw.topic == sel.ir {
            let m: Image = BagReader::decode(&raw)?;
            ir.insert(m.header.stamp.as_log_time_ns(), m);
        } else if Some(raw.topic) == sel.info.as_deref() && info.is_none() {
            info = Some(BagReader::decode::<CameraInfo>(&raw)?);
        }
    }
    let info = info.ok_or_else(|| anyhow!("{}: no camera_info", path.display()))?;
    let pairs = depth
        .into_iter()
        .filter_map(|(s, d)| ir.remove(&s).map(|i| (d, i)))
        .collect();
    Ok((info, pairs))
}

/// What the peer received from the node.
#[derive(Debug, Default)]
pub struct Received {
    /// `~/depth/corrected` by stamp (ns).
    pub corrected: BTreeMap<u64, Image>,
    /// `~/translucent_mask` by stamp.
    pub mask: BTreeMap<u64, Image>,
    /// `~/depth/corrected_sigma` by stamp.
    pub sigma: BTreeMap<u64, Image>,
    /// `~/depth/camera_info` by stamp.
    pub camera_info: BTreeMap<u64, CameraInfo>,
    /// `~/points` by stamp.
    pub points: BTreeMap<u64, PointCloud2>,
    /// `~/translucency` in arrival order.
    pub estimates: Vec<TranslucencyEstimate>,
    /// When each corrected depth arrived (for latency), by stamp.
    pub arrival: BTreeMap<u64, std::time::Instant>,
}

/// A driver + client + listener on the node's graph.
pub struct Peer {
    node: Node,
    depth: Publisher<Image>,
    ir: Publisher<Image>,
    info: Publisher<CameraInfo>,
    latch: Client<TriggerRequest, TriggerResponse>,
    clear: Client<TriggerRequest, TriggerResponse>,
    corrected: Subscription<Image>,
    mask: Subscription<Image>,
    sigma: Subscription<Image>,
    camera_info: Subscription<CameraInfo>,
    points: Subscription<PointCloud2>,
    estimate: Subscription<TranslucencyEstimate>,
    /// Everything received so far.
    pub received: Received,
}

fn name(full: &str) -> Result<Name> {
    Name::parse(full).map_err(|e| anyhow!("ROS name {full:?}: {e:?}"))
}

impl Peer {
    /// A peer for the node `node_fqn` whose inputs live in `namespace`
    /// (e.g. `/tof` and `/tof/translucent_tof`). Call from inside a Tokio runtime.
    pub fn new(
        ctx: &ros2_client::Context,
        peer_name: &str,
        namespace: &str,
        node_fqn: &str,
        mapping: ServiceMapping,
    ) -> Result<Self> {
        let mut node = ctx
            .new_node(
                NodeName::new("/", peer_name).map_err(|e| anyhow!("{e:?}"))?,
                NodeOptions::new().enable_rosout(false),
            )
            .map_err(|e| anyhow!("peer node: {e:?}"))?;
        let spinner = node.spinner().map_err(|e| anyhow!("{e:?}"))?;
        tokio::spawn(spinner.spin());
        let ns = namespace.trim_end_matches('/');
        // A driver's sensor-data QoS; the listener is reliable for the outputs.
        let sensor = QosProfile::subscription_default().history(History::KeepLast { depth: 5 });
        let driver = QosProfile::publisher_default().history(History::KeepLast { depth: 5 });
        let listen = QosProfile::publisher_default().history(History::KeepLast { depth: 50 });
        let latched = QosProfile::publisher_default()
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 50 });
        let topic = |full: String, pkg: &str, ty: &str, qos: &QosProfile| {
            node.create_topic(&name(&full)?, MessageTypeName::new(pkg, ty), qos)
                .map_err(|e| anyhow!("topic {full}: {e:?}"))
        };
        let t_depth = topic(format!("{ns}/depth/image_raw"), "sensor_msgs", "Image", &sensor)?;
        let t_ir = topic(format!("{ns}/ir/image_raw"), "sensor_msgs", "Image", &sensor)?;
        let t_info = topic(format!("{ns}/depth/camera_info"), "sensor_msgs", "CameraInfo", &sensor)?;
        let t_corr = topic(format!("{node_fqn}/depth/corrected"), "sensor_msgs", "Image", &listen)?;
        let t_mask = topic(format!("{node_fqn}/translucent_mask"), "sensor_msgs", "Image", &listen)?;
        let t_sigma = topic(
            format!("{node_fqn}/depth/corrected_sigma"),
            "sensor_msgs",
            "Image",
            &listen,
        )?;
        let t_info_out = topic(
            format!("{node_fqn}/depth/camera_info"),
            "sensor_msgs",
            "CameraInfo",
            &listen,
        )?;
        let t_points = topic(format!("{node_fqn}/points"), "sensor_msgs", "PointCloud2", &listen)?;
        let t_est = topic(
            format!("{node_fqn}/translucency"),
            crate::msgs::translucent_tof::PACKAGE,
            "TranslucencyEstimate",
            &latched,
        )?;
        let e = |what: &'static str| move |err| anyhow!("{what}: {err:?}");
        let trigger = ServiceTypeName::new("std_srvs", "Trigger");
        let srv_q = QosProfile::publisher_default().history(History::KeepLast { depth: 10 });
        Ok(Self {
            depth: node
                .create_publisher(&t_depth, Some(driver.clone()))
                .map_err(e("depth publisher"))?,
            ir: node
                .create_publisher(&t_ir, Some(driver.clone()))
                .map_err(e("IR publisher"))?,
            info: node
                .create_publisher(&t_info, Some(driver))
                .map_err(e("camera_info publisher"))?,
            latch: node
                .create_client(
                    mapping,
                    &name(&format!("{node_fqn}/latch_background"))?,
                    &trigger,
                    srv_q.clone(),
                    srv_q.clone(),
                )
                .map_err(e("latch client"))?,
            clear: node
                .create_client(
                    mapping,
                    &name(&format!("{node_fqn}/clear_background"))?,
                    &trigger,
                    srv_q.clone(),
                    srv_q,
                )
                .map_err(e("clear client"))?,
            corrected: node
                .create_subscription(&t_corr, Some(listen.clone()))
                .map_err(e("corrected subscription"))?,
            mask: node
                .create_subscription(&t_mask, Some(listen.clone()))
                .map_err(e("mask subscription"))?,
            sigma: node
                .create_subscription(&t_sigma, Some(listen.clone()))
                .map_err(e("sigma subscription"))?,
            camera_info: node
                .create_subscription(&t_info_out, Some(listen.clone()))
                .map_err(e("camera_info subscription"))?,
            points: node
                .create_subscription(&t_points, Some(listen))
                .map_err(e("points subscription"))?,
            estimate: node
                .create_subscription(&t_est, Some(latched))
                .map_err(e("estimate subscription"))?,
            node,
            received: Received::default(),
        })
    }

    /// Waits until the node's inputs and outputs have matched ours and its
    /// latch service is there.
    pub async fn wait_for_node(&self, timeout: Duration) -> Result<()> {
        let all = async {
            rearmed(|| self.depth.wait_for_subscription(&self.node)).await;
            rearmed(|| self.ir.wait_for_subscription(&self.node)).await;
            rearmed(|| self.info.wait_for_subscription(&self.node)).await;
            rearmed(|| self.corrected.wait_for_publisher(&self.node)).await;
            rearmed(|| self.points.wait_for_publisher(&self.node)).await;
            rearmed(|| self.estimate.wait_for_publisher(&self.node)).await;
            rearmed(|| self.latch.wait_for_service(&self.node)).await;
            rearmed(|| self.clear.wait_for_service(&self.node)).await;
        };
        tokio::time::timeout(timeout, all)
            .await
            .map_err(|_| anyhow!("the node did not appear on DDS within {:.0} s", timeout.as_secs_f64()))
    }

    /// Waits until the node's mask, sigma and camera_info beside the corrected depth have
    /// matched ours too (after [`Self::wait_for_node`]; a stand-in that publishes fewer
    /// outputs, as the latency bench's echo, never gets there).
    pub async fn wait_for_every_output(&self, timeout: Duration) -> Result<()> {
        let all = async {
            rearmed(|| self.mask.wait_for_publisher(&self.node)).await;
            rearmed(|| self.sigma.wait_for_publisher(&self.node)).await;
            rearmed(|| self.camera_info.wait_for_publisher(&self.node)).await;
        };
        tokio::time::timeout(timeout, all).await.map_err(|_| {
            anyhow!(
                "the node's mask, sigma and camera_info outputs did not match within {:.0} s",
                timeout.as_secs_f64()
            )
        })
    }

    /// Publishes one frame as a driver would: camera_info, depth, IR.
    pub fn publish(&self, info: &CameraInfo, depth: &Image, ir: &Image) -> Result<()> {
        self.info
            .publish(info.clone())
            .map_err(|e| anyhow!("camera_info: {e:?}"))?;
        self.depth.publish(depth.clone()).map_err(|e| anyhow!("depth: {e:?}"))?;
        self.ir.publish(ir.clone()).map_err(|e| anyhow!("IR: {e:?}"))?;
        Ok(())
    }

    /// Publishes a single image on the depth or IR topic (fault tests).
    pub fn publish_one(&self, depth: bool, img: &Image) -> Result<()> {
        let p = if depth { &self.depth } else { &self.ir };
        p.publish(img.clone()).map_err(|e| anyhow!("{e:?}"))
    }

    /// Publishes a camera_info alone.
    pub fn publish_info(&self, info: &CameraInfo) -> Result<()> {
        self.info.publish(info.clone()).map_err(|e| anyhow!("{e:?}"))
    }

    /// Calls `~/latch_background` (`latch = true`) or `~/clear_background`.
    pub async fn call(&self, latch: bool, timeout: Duration) -> Result<TriggerResponse> {
        let c = if latch { &self.latch } else { &self.clear };
        let req = TriggerRequest::default();
        tokio::time::timeout(timeout, c.async_call_service(req))
            .await
            .map_err(|_| anyhow!("no reply within {:.0} s", timeout.as_secs_f64()))?
            .map_err(|e| anyhow!("service call: {e:?}"))
    }

    /// Calls `~/latch_background` while streaming `background` (cycling,
    /// restamped from `stamp_ns` on, `period_ns` apart, every `period`), as
    /// a driver keeps streaming the empty scene during the latch.
    pub async fn latch_while_streaming(
        &self,
        info: &CameraInfo,
        background: &[(Image, Image)],
        period: Duration,
        stamp_ns: &mut u64,
        period_ns: u64,
    ) -> Result<TriggerResponse> {
        if background.is_empty() {
            return Err(anyhow!("no background frames to stream"));
        }
        let mut tick = tokio::time::interval(period);
        let mut k = 0;
        let send = |k: usize, stamp_ns: &mut u64| -> Result<()> {
            let (d, i) = &background[k % background.len()];
            *stamp_ns += period_ns;
            let mut info = info.clone();
            info.header = Header::new(*stamp_ns, info.header.frame_id.clone());
            self.publish(&info, &restamp(d, *stamp_ns), &restamp(i, *stamp_ns))
        };
        // A driver is streaming before anyone latches: the node has camera_info by then.
        for _ in 0..2 {
            tick.tick().await;
            send(k, stamp_ns)?;
            k += 1;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        let call = self.call(true, Duration::from_secs(60));
        tokio::pin!(call);
        loop {
            tokio::select! {
                r = &mut call => return r,
                _ = tick.tick() => {
                    send(k, stamp_ns)?;
                    k += 1;
                }
            }
        }
    }

    /// Stamps of `~/depth/corrected` as they arrive, with their arrival time
    /// (woken by DDS, not polled: for latency measurements).
    pub fn corrected_arrivals(&self) -> impl futures::Stream<Item = (u64, std::time::Instant)> + '_ {
        use futures::StreamExt;
        self.corrected.async_stream().filter_map(|m| async move {
            m.ok()
                .map(|(img, _)| (img.header.stamp.as_log_time_ns(), std::time::Instant::now()))
        })
    }

    /// Takes whatever outputs have arrived.
    pub fn drain(&mut self) {
        while let Ok(Some((m, _))) = self.corrected.take() {
            let s = m.header.stamp.as_log_time_ns();
            self.received.arrival.insert(s, std::time::Instant::now());
            self.received.corrected.insert(s, m);
        }
        while let Ok(Some((m, _))) = self.mask.take() {
            self.received.mask.insert(m.header.stamp.as_log_time_ns(), m);
        }
        while let Ok(Some((m, _))) = self.sigma.take() {
            self.received.sigma.insert(m.header.stamp.as_log_time_ns(), m);
        }
        while let Ok(Some((m, _))) = self.camera_info.take() {
            self.received.camera_info.insert(m.header.stamp.as_log_time_ns(), m);
        }
        while let Ok(Some((m, _))) = self.points.take() {
            self.received.points.insert(m.header.stamp.as_log_time_ns(), m);
        }
        while let Ok(Some((m, _))) = self.estimate.take() {
            self.received.estimates.push(m);
        }
    }

    /// Drains until `stamp` has its corrected depth, or `timeout`.
    pub async fn wait_for(&mut self, stamp: u64, timeout: Duration) -> bool {
        self.wait_until(timeout, |r| r.corrected.contains_key(&stamp)).await
    }

    /// Drains until `stamp` has its corrected depth, mask, sigma and camera_info (each a
    /// separate DDS writer, so they arrive in no fixed order), or `timeout`.
    pub async fn wait_for_every(&mut self, stamp: u64, timeout: Duration) -> bool {
        self.wait_until(timeout, |r| {
            r.corrected.contains_key(&stamp)
                && r.mask.contains_key(&stamp)
                && r.sigma.contains_key(&stamp)
                && r.camera_info.contains_key(&stamp)
        })
        .await
    }

    async fn wait_until(&mut self, timeout: Duration, done: impl Fn(&Received) -> bool) -> bool {
        let until = tokio::time::Instant::now() + timeout;
        loop {
            self.drain();
            if done(&self.received) {
                return true;
            }
            if tokio::time::Instant::now() >= until {
                return false;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
}
