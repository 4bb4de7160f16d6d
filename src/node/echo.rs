//! The transport baseline of the latency benchmark: a bare DDS
//! subscriber/publisher under the node's names that answers each frame, as
//! soon as both its depth and IR images are in (paired by stamp, as the node
//! pairs them), with the same messages the node would send (the depth image,
//! a mask and an organized cloud of the same size, an estimate), with no
//! queue or pipeline. The node's added latency is measured against it.

use std::time::Duration;

use anyhow::{anyhow, Result};
use futures::StreamExt;
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, QosProfile, ServiceMapping, ServiceTypeName};

use super::inbox::StampPairer;
use crate::image::{mask_image, organized_cloud};
use crate::msgs::translucent_tof::TranslucencyEstimate;
use crate::msgs::{Image, PointCloud2, TriggerRequest, TriggerResponse};
use crate::physics::ImageBuf;

fn name(s: &str) -> Result<Name> {
    Name::parse(s).map_err(|e| anyhow!("{s}: {e:?}"))
}

/// Runs the echo for `namespace` / `node_fqn` until SIGINT / SIGTERM.
pub fn run(domain_id: u16, namespace: &str, node_fqn: &str) -> Result<()> {
    let localhost_only = std::env::var("ROS_LOCALHOST_ONLY").is_ok_and(|v| v.trim() == "1");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let ctx = super::context(domain_id, localhost_only)?;
        let (base, ns) = node_fqn
            .rsplit_once('/')
            .map(|(ns, b)| {
                (
                    b.to_string(),
                    if ns.is_empty() { "/".to_string() } else { ns.to_string() },
                )
            })
            .ok_or_else(|| anyhow!("node name {node_fqn:?} is not absolute"))?;
        let mut node = ctx
            .new_node(
                NodeName::new(&ns, &base).map_err(|e| anyhow!("{e:?}"))?,
                NodeOptions::new(),
            )
            .map_err(|e| anyhow!("{e:?}"))?;
        let spinner = node.spinner().map_err(|e| anyhow!("{e:?}"))?;
        tokio::spawn(spinner.spin());
        let sensor = super::qos_sensor();
        let out_q = super::qos_outputs();
        let ns_in = namespace.trim_end_matches('/');
        let topic = |full: String, pkg: &str, ty: &str, q: &QosProfile| {
            node.create_topic(&name(&full)?, MessageTypeName::new(pkg, ty), q)
                .map_err(|e| anyhow!("{full}: {e:?}"))
        };
        let t_in = topic(format!("{ns_in}/depth/image_raw"), "sensor_msgs", "Image", &sensor)?;
        let t_ir = topic(format!("{ns_in}/ir/image_raw"), "sensor_msgs", "Image", &sensor)?;
        let t_info = topic(
            format!("{ns_in}/depth/camera_info"),
            "sensor_msgs",
            "CameraInfo",
            &sensor,
        )?;
        let t_out = topic(format!("{node_fqn}/depth/corrected"), "sensor_msgs", "Image", &out_q)?;
        let t_mask = topic(format!("{node_fqn}/translucent_mask"), "sensor_msgs", "Image", &out_q)?;
        let t_pts = topic(format!("{node_fqn}/points"), "sensor_msgs", "PointCloud2", &out_q)?;
        let est_q = super::qos_estimate();
        let t_est = topic(
            format!("{node_fqn}/translucency"),
            crate::msgs::translucent_tof::PACKAGE,
            "TranslucencyEstimate",
            &est_q,
        )?;
        let e = |err| anyhow!("{err:?}");
        let sub = node
            .create_subscription::<Image>(&t_in, Some(sensor.clone()))
            .map_err(e)?;
        let ir_sub = node
            .create_subscription::<Image>(&t_ir, Some(sensor.clone()))
            .map_err(e)?;
        let _info = node
            .create_subscription::<crate::msgs::CameraInfo>(&t_info, Some(sensor))
            .map_err(e)?;
        let p_out = node.create_publisher::<Image>(&t_out, Some(out_q.clone())).map_err(e)?;
        let p_mask = node
            .create_publisher::<Image>(&t_mask, Some(out_q.clone()))
            .map_err(e)?;
        let p_pts = node.create_publisher::<PointCloud2>(&t_pts, Some(out_q)).map_err(e)?;
        let p_est = node
            .create_publisher::<TranslucencyEstimate>(&t_est, Some(est_q))
            .map_err(e)?;
        let trigger = ServiceTypeName::new("std_srvs", "Trigger");
        let sq = super::qos_service();
        let mk = |n: &str| name(&format!("{node_fqn}/{n}"));
        let latch = node
            .create_server::<TriggerRequest, TriggerResponse>(
                ServiceMapping::Enhanced,
                &mk("latch_background")?,
                &trigger,
                sq.clone(),
                sq.clone(),
            )
            .map_err(e)?;
        let clear = node
            .create_server::<TriggerRequest, TriggerResponse>(
                ServiceMapping::Enhanced,
                &mk("clear_background")?,
                &trigger,
                sq.clone(),
                sq,
            )
            .map_err(e)?;
        let mut depths = std::pin::pin!(sub.async_stream());
        let mut irs = std::pin::pin!(ir_sub.async_stream());
        // A frame is in when both of its images are: the node cannot start before that either.
        let mut pairer = StampPairer::new(4);
        let mut latches = std::pin::pin!(latch.receive_request_stream());
        let mut clears = std::pin::pin!(clear.receive_request_stream());
        // Made once: a `ctrl_c()` made anew each turn misses a signal that arrives mid-turn.
        let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())?;
        let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        let ok = || TriggerResponse {
            success: true,
            message: "echo".into(),
        };
        // Outputs of each size are built once; each frame only restamps them.
        let mut template: Option<(u32, u32, PointCloud2, Image)> = None;
        let mut answer = |img: Image| {
            if template.as_ref().is_none_or(|t| (t.0, t.1) != (img.width, img.height)) {
                let (w, h) = (img.width as usize, img.height as usize);
                let mask = ImageBuf::filled(w, h, false);
                let xyz = ImageBuf::filled(w, h, [0.0f32, 0.0, 1.0]);
                let cloud = organized_cloud(
                    &img.header,
                    &xyz,
                    &ImageBuf::filled(w, h, 0.0f32),
                    &mask,
                    &ImageBuf::filled(w, h, f32::NAN),
                );
                template = Some((img.width, img.height, cloud, mask_image(&img.header, &mask)));
            }
            let Some((_, _, cloud, m_img)) = &template else { return };
            let (mut cloud, mut m_img) = (cloud.clone(), m_img.clone());
            cloud.header = img.header.clone();
            m_img.header = img.header.clone();
            let est = TranslucencyEstimate {
                header: img.header.clone(),
                xi: 0.0,
                xi_lower: 0.0,
                xi_upper: 0.0,
                method: "echo".into(),
                translucent_pixels: 0,
                fit_residual_mm: 0.0,
                frames_pooled: 0,
                region_id: 0,
                region_pixels: 0,
                opaque: false,
                material: String::new(),
                class_probability: f64::NAN,
            };
            let _ = p_out.publish(img);
            let _ = p_mask.publish(m_img);
            let _ = p_pts.publish(cloud);
            let _ = p_est.publish(est);
        };
        loop {
            tokio::select! {
                m = depths.next() => {
                    let Some(Ok((img, _))) = m else { continue };
                    let Some((img, _)) = pairer.depth(img) else { continue };
                    answer(img);
                }
                m = irs.next() => {
                    let Some(Ok((ir, _))) = m else { continue };
                    let Some((img, _)) = pairer.ir(ir) else { continue };
                    answer(img);
                }
                Some(Ok((id, _))) = latches.next() => { let _ = latch.async_send_response(id, ok()).await; }
                Some(Ok((id, _))) = clears.next() => { let _ = clear.async_send_response(id, ok()).await; }
                _ = sigint.recv() => break,
                _ = sigterm.recv() => break,
                _ = tokio::time::sleep(Duration::from_secs(3600)) => {}
            }
        }
        Ok(())
    })
}
