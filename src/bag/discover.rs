//! Which topics of a bag hold depth, IR, camera info and ground truth.
//!
//! By type first (`sensor_msgs/msg/Image`, `sensor_msgs/msg/CameraInfo`),
//! then by the names of the interface (`depth/image_raw`, `ir/image_raw`,
//! `depth/camera_info`, `ground_truth/depth`) under any namespace, then by
//! looser names. Two equally good candidates are an error that asks for
//! `--depth-topic` / `--ir-topic` / `--info-topic`.

use super::{normalize_type_name, BagError, TopicInfo};

const IMAGE: &str = "sensor_msgs/msg/Image";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

/// Topics given on the command line, overriding discovery.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TopicOverrides {
    /// `--depth-topic`.
    pub depth: Option<String>,
    /// `--ir-topic`.
    pub ir: Option<String>,
    /// `--info-topic`.
    pub info: Option<String>,
}

/// The topics chosen for a replay, and why.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SelectedTopics {
    /// Depth images (`sensor_msgs/msg/Image`).
    pub depth: String,
    /// IR / intensity images (`sensor_msgs/msg/Image`).
    pub ir: String,
    /// Intrinsics (`sensor_msgs/msg/CameraInfo`), when the bag has them.
    pub info: Option<String>,
    /// Ground-truth z-depth (`sensor_msgs/msg/Image`, `32FC1` m), when present.
    pub ground_truth: Option<String>,
    /// Sentences saying which topic was chosen for what, and why.
    pub notes: Vec<String>,
}

/// True when `topic` ends with the name segments of `suffix`.
fn ends_with_segments(topic: &str, suffix: &str) -> bool {
    let topic = topic.trim_start_matches('/');
    topic == suffix || topic.ends_with(&format!("/{suffix}"))
}

fn segments(topic: &str) -> impl Iterator<Item = &str> {
    topic.split('/').filter(|s| !s.is_empty())
}

/// The camera namespace of a topic: trailing stream and image segments
/// removed. `/tof/depth/image_raw`, `/tof/depth/camera_info`,
/// `/tof/camera_info` and `/tof/ground_truth/depth` → `/tof`.
pub(super) fn camera_namespace(topic: &str) -> String {
    let mut segs: Vec<&str> = segments(topic).collect();
    let is_leaf = |s: &str| {
        s.starts_with("image")
            || s == "camera_info"
            || is_ir_segment(s)
            || [
                "depth",
                "intensity",
                "amplitude",
                "infra",
                "color",
                "rgb",
                "confidence",
                "ground_truth",
            ]
            .iter()
            .any(|w| s.contains(w))
    };
    while segs.last().is_some_and(|s| is_leaf(s)) {
        segs.pop();
    }
    format!("/{}", segs.join("/"))
}

/// This tool's own outputs and ground truth: never an input.
fn is_excluded(topic: &str) -> bool {
    ends_with_segments(topic, "ground_truth/depth")
        || ends_with_segments(topic, "depth/corrected")
        || ends_with_segments(topic, "translucent_mask")
        || topic.contains("ground_truth")
}

fn depth_rank(topic: &str) -> Option<(u8, &'static str)> {
    if is_excluded(topic) {
        return None;
    }
    const ENDINGS: [&str; 5] = [
        "depth/image_raw",
        "depth/image_rect_raw",
        "depth/image",
        "depth/image_rect",
        "depth",
    ];
    for (rank, ending) in ENDINGS.iter().enumerate() {
        if ends_with_segments(topic, ending) {
            return Some((rank as u8, ending));
        }
    }
    topic.contains("depth").then_some((ENDINGS.len() as u8, "depth"))
}

fn is_ir_segment(seg: &str) -> bool {
    // `ir`, `ir1`, `ir_image`: an `ir` not followed by a letter.
    seg.strip_prefix("ir")
        .is_some_and(|rest| !rest.starts_with(|c: char| c.is_ascii_alphabetic()))
}

fn ir_rank(topic: &str) -> Option<(u8, &'static str)> {
    if is_excluded(topic) || topic.contains("depth") || topic.contains("confidence") {
        return None;
    }
    if ends_with_segments(topic, "ir/image_raw") {
        return Some((0, "ir/image_raw"));
    }
    for ending in ["ir/image_rect_raw", "ir/image", "ir/image_rect"] {
        if ends_with_segments(topic, ending) {
            return Some((1, ending));
        }
    }
    if segments(topic).any(is_ir_segment) {
        return Some((2, "ir"));
    }
    for word in ["intensity", "amplitude", "infra"] {
        if topic.contains(word) {
            return Some((3, word));
        }
    }
    None
}

fn list_topics(topics: &[TopicInfo]) -> String {
    if topics.is_empty() {
        return "no topics".to_string();
    }
    topics
        .iter()
        .map(|t| format!("{} ({}, {} msgs)", t.name, t.type_name, t.message_count))
        .collect::<Vec<_>>()
        .join(", ")
}

/// A candidate: the topic, its sort key (lower is better) and why it fits.
type Candidate<'a> = (&'a TopicInfo, (u8, u8), String);

/// The single best candidate; `Ok(None)` when there is none.
fn best<'a>(
    mut candidates: Vec<Candidate<'a>>,
    role: &'static str,
    flag: &'static str,
) -> Result<Option<Candidate<'a>>, BagError> {
    candidates.sort_by(|a, b| a.1.cmp(&b.1).then_with(|| a.0.name.cmp(&b.0.name)));
    let Some(first) = candidates.first() else {
        return Ok(None);
    };
    let tied: Vec<String> = candidates
        .iter()
        .filter(|c| c.1 == first.1)
        .map(|c| c.0.name.clone())
        .collect();
    if tied.len() > 1 {
        return Err(BagError::AmbiguousTopic {
            role,
            candidates: tied,
            flag,
        });
    }
    Ok(candidates.into_iter().next())
}

/// The override's topic, checked to be in the bag with type `want`.
fn overridden<'a>(
    topics: &'a [TopicInfo],
    name: &str,
    want: &str,
    flag: &'static str,
) -> Result<&'a TopicInfo, BagError> {
    let bare = name.trim_start_matches('/');
    let found = topics
        .iter()
        .find(|t| t.name == name || t.name.trim_start_matches('/') == bare);
    let bad = |problem: String| BagError::BadOverride {
        flag,
        topic: name.to_string(),
        problem,
        available: list_topics(topics),
    };
    match found {
        None => Err(bad("no such topic in the bag".to_string())),
        Some(t) if normalize_type_name(&t.type_name) != want => {
            Err(bad(format!("it has type {}, not {want}", t.type_name)))
        }
        Some(t) => Ok(t),
    }
}

/// Chooses the depth, IR, camera-info and ground-truth topics of a bag.
///
/// Overrides win (and must name a topic of the right type); otherwise:
/// depth is the `Image` topic ending in `depth/image_raw`, else
/// `depth/image_rect_raw`, `depth/image`, `depth/image_rect`, `depth`, else
/// containing `depth` (never `ground_truth/depth` nor `depth/corrected`);
/// IR ends in `ir/image_raw`, else `ir/image_rect_raw`, `ir/image`,
/// `ir/image_rect`, else has an `ir` name segment, else contains
/// `intensity`, `amplitude` or `infra` (never `depth` or `confidence`);
/// info is `depth/camera_info` in the depth topic's namespace, else any
/// `CameraInfo` there, else `depth/camera_info` elsewhere, else the only
/// `CameraInfo`; ground truth ends in `ground_truth/depth`. Among equally
/// named candidates, the depth topic's namespace wins.
pub fn select_topics(topics: &[TopicInfo], ov: &TopicOverrides) -> Result<SelectedTopics, BagError> {
    let of_type = |want: &'static str| topics.iter().filter(move |t| normalize_type_name(&t.type_name) == want);
    let mut notes = Vec::new();

    // IR override first: it can settle the depth topic's namespace.
    let ir_override = match &ov.ir {
        Some(name) => Some(overridden(topics, name, IMAGE, "--ir-topic")?),
        None => None,
    };

    let depth = match &ov.depth {
        Some(name) => {
            let t = overridden(topics, name, IMAGE, "--depth-topic")?;
            notes.push(format!("depth: {} (given by --depth-topic)", t.name));
            t
        }
        None => {
            let ir_ns = ir_override.map(|t| camera_namespace(&t.name));
            let candidates = of_type(IMAGE)
                .filter(|t| ir_override.is_none_or(|ir| ir.name != t.name))
                .filter_map(|t| {
                    let (rank, why) = depth_rank(&t.name)?;
                    let other_ns = u8::from(ir_ns.as_ref().is_some_and(|ns| *ns != camera_namespace(&t.name)));
                    Some((t, (rank, other_ns), why.to_string()))
                })
                .collect();
            match best(candidates, "depth", "--depth-topic")? {
                Some((t, _, why)) => {
                    let how = if why == "depth" && !ends_with_segments(&t.name, "depth") {
                        "its name contains \"depth\"".to_string()
                    } else {
                        format!("its name ends with {why}")
                    };
                    notes.push(format!("depth: {} ({how}, sensor_msgs/msg/Image)", t.name));
                    t
                }
                None => {
                    return Err(BagError::NoTopic {
                        role: "depth",
                        looked_for: "a sensor_msgs/msg/Image topic named like depth/image_raw",
                        available: list_topics(topics),
                        flag: "--depth-topic",
                    })
                }
            }
        }
    };
    let ns = camera_namespace(&depth.name);
    let other_ns = |t: &TopicInfo| u8::from(camera_namespace(&t.name) != ns);

    let ir = match ir_override {
        Some(t) => {
            notes.push(format!("IR: {} (given by --ir-topic)", t.name));
            t
        }
        None => {
            let candidates = of_type(IMAGE)
                .filter(|t| t.name != depth.name)
                .filter_map(|t| {
                    let (rank, why) = ir_rank(&t.name)?;
                    Some((t, (rank, other_ns(t)), why.to_string()))
                })
                .collect();
            match best(candidates, "IR", "--ir-topic")? {
                Some((t, (rank, _), why)) => {
                    let how = match rank {
                        0 | 1 => format!("its name ends with {why}"),
                        2 => "it has an \"ir\" name segment".to_string(),
                        _ => format!("its name contains \"{why}\""),
                    };
                    notes.push(format!("IR: {} ({how}, sensor_msgs/msg/Image)", t.name));
                    t
                }
                None => {
                    return Err(BagError::NoTopic {
                        role: "IR",
                        looked_for: "a sensor_msgs/msg/Image topic named like ir/image_raw, or with ir, intensity or amplitude in its name",
                        available: list_topics(topics),
                        flag: "--ir-topic",
                    })
                }
            }
        }
    };

    let info = match &ov.info {
        Some(name) => {
            let t = overridden(topics, name, CAMERA_INFO, "--info-topic")?;
            notes.push(format!("camera info: {} (given by --info-topic)", t.name));
            Some(t.name.clone())
        }
        None => {
            let infos: Vec<&TopicInfo> = of_type(CAMERA_INFO).collect();
            let only_one = infos.len() == 1;
            let candidates = infos
                .iter()
                .filter_map(|&t| {
                    let named = ends_with_segments(&t.name, "depth/camera_info");
                    let (rank, why) = match (named, other_ns(t) == 0) {
                        (true, true) => (0, format!("ends with depth/camera_info in {ns}")),
                        (false, true) => (1, format!("the camera info in the depth topic's namespace {ns}")),
                        (true, false) => (2, "ends with depth/camera_info".to_string()),
                        (false, false) if only_one => (3, "the only camera info in the bag".to_string()),
                        (false, false) => return None,
                    };
                    Some((t, (rank, 0), why))
                })
                .collect();
            match best(candidates, "camera info", "--info-topic")? {
                Some((t, _, why)) => {
                    notes.push(format!("camera info: {} ({why})", t.name));
                    Some(t.name.clone())
                }
                None if infos.is_empty() => {
                    notes.push("camera info: none in the bag".to_string());
                    None
                }
                None => {
                    notes.push(format!(
                        "camera info: none chosen; {} do not match the depth topic's namespace {ns} (pass --info-topic)",
                        infos.iter().map(|t| t.name.as_str()).collect::<Vec<_>>().join(", ")
                    ));
                    None
                }
            }
        }
    };

    let truths: Vec<Candidate> = of_type(IMAGE)
        .filter(|t| ends_with_segments(&t.name, "ground_truth/depth"))
        .map(|t| (t, (other_ns(t), 0), String::new()))
        .collect();
    let ground_truth = match best(truths, "ground truth", "") {
        Ok(Some((t, _, _))) => {
            notes.push(format!("ground truth: {} (ends with ground_truth/depth)", t.name));
            Some(t.name.clone())
        }
        Ok(None) => None,
        Err(BagError::AmbiguousTopic { candidates, .. }) => {
            notes.push(format!(
                "ground truth: none used; {} are equally likely",
                candidates.join(", ")
            ));
            None
        }
        Err(e) => return Err(e),
    };

    Ok(SelectedTopics {
        depth: depth.name.clone(),
        ir: ir.name.clone(),
        info,
        ground_truth,
        notes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn topic(name: &str, type_name: &str) -> TopicInfo {
        TopicInfo {
            name: name.into(),
            type_name: type_name.into(),
            message_count: 3,
        }
    }
    fn img(name: &str) -> TopicInfo {
        topic(name, IMAGE)
    }
    fn info(name: &str) -> TopicInfo {
        topic(name, CAMERA_INFO)
    }
    fn select(topics: &[TopicInfo]) -> Result<SelectedTopics, BagError> {
        select_topics(topics, &TopicOverrides::default())
    }

    #[test]
    fn interface_names_under_a_namespace() {
        let topics = [
            img("/tof/depth/image_raw"),
            img("/tof/ir/image_raw"),
            info("/tof/depth/camera_info"),
            img("/tof/ground_truth/depth"),
            topic("/tf", "tf2_msgs/msg/TFMessage"),
        ];
        let s = select(&topics).unwrap();
        assert_eq!(s.depth, "/tof/depth/image_raw");
        assert_eq!(s.ir, "/tof/ir/image_raw");
        assert_eq!(s.info.as_deref(), Some("/tof/depth/camera_info"));
        assert_eq!(s.ground_truth.as_deref(), Some("/tof/ground_truth/depth"));
        assert_eq!(s.notes.len(), 4, "{:?}", s.notes);
        assert!(s.notes[0].contains("ends with depth/image_raw"), "{:?}", s.notes);
    }

    #[test]
    fn short_type_names_are_accepted() {
        let topics = [
            topic("/depth/image_raw", "sensor_msgs/Image"),
            topic("/ir/image_raw", "sensor_msgs/Image"),
        ];
        let s = select(&topics).unwrap();
        assert_eq!((s.depth.as_str(), s.ir.as_str()), ("/depth/image_raw", "/ir/image_raw"));
        assert_eq!(s.info, None);
    }

    #[test]
    fn depth_name_preference_order() {
        let topics = [
            img("/cam/depth/image_rect"),
            img("/cam/depth/image_rect_raw"),
            img("/cam/aligned_depth_to_color/foo"),
            img("/cam/ir/image_raw"),
        ];
        assert_eq!(select(&topics).unwrap().depth, "/cam/depth/image_rect_raw");
        let topics = [img("/cam/aligned_depth_to_color/foo"), img("/cam/ir/image_raw")];
        let s = select(&topics).unwrap();
        assert_eq!(s.depth, "/cam/aligned_depth_to_color/foo");
        assert!(s.notes[0].contains("contains \"depth\""), "{:?}", s.notes);
        let topics = [img("/cam/depth"), img("/cam/intensity")];
        let s = select(&topics).unwrap();
        assert_eq!((s.depth.as_str(), s.ir.as_str()), ("/cam/depth", "/cam/intensity"));
    }

    #[test]
    fn depth_never_ground_truth_or_own_output() {
        let topics = [
            img("/tof/ground_truth/depth"),
            img("/translucent_tof/depth/corrected"),
            img("/tof/ir/image_raw"),
        ];
        let err = select(&topics).unwrap_err();
        assert!(matches!(err, BagError::NoTopic { role: "depth", .. }), "{err}");
        let msg = err.to_string();
        assert!(
            msg.contains("/tof/ir/image_raw") && msg.contains("--depth-topic"),
            "{msg}"
        );
    }

    #[test]
    fn depth_must_be_an_image() {
        let topics = [
            topic("/tof/depth/image_raw", "sensor_msgs/msg/CompressedImage"),
            img("/tof/ir/image_raw"),
        ];
        assert!(matches!(select(&topics), Err(BagError::NoTopic { role: "depth", .. })));
    }

    #[test]
    fn ir_rules() {
        let base = img("/cam/depth/image_raw");
        let cases = [
            (
                vec![img("/cam/ir/image_rect_raw"), img("/cam/amplitude")],
                "/cam/ir/image_rect_raw",
            ),
            (
                vec![img("/cam/ir1/image_raw_x"), img("/cam/amplitude")],
                "/cam/ir1/image_raw_x",
            ),
            (
                vec![img("/cam/amplitude"), img("/cam/confidence/image")],
                "/cam/amplitude",
            ),
            (vec![img("/cam/infra1/image_rect_raw")], "/cam/infra1/image_rect_raw"),
        ];
        for (extra, want) in cases {
            let mut topics = vec![base.clone()];
            topics.extend(extra);
            assert_eq!(select(&topics).unwrap().ir, want, "{topics:?}");
        }
        // "mirror" is not IR; confidence never is.
        let topics = [base.clone(), img("/cam/mirror/image"), img("/cam/confidence")];
        let err = select(&topics).unwrap_err();
        assert!(matches!(err, BagError::NoTopic { role: "IR", .. }), "{err}");
        assert!(err.to_string().contains("/cam/mirror/image"), "{err}");
    }

    #[test]
    fn ambiguity_is_an_error_naming_candidates_and_flag() {
        let topics = [
            img("/a/depth/image_raw"),
            img("/b/depth/image_raw"),
            img("/a/ir/image_raw"),
        ];
        let err = select(&topics).unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("/a/depth/image_raw") && msg.contains("/b/depth/image_raw"),
            "{msg}"
        );
        assert!(msg.contains("--depth-topic"), "{msg}");
    }

    #[test]
    fn namespace_breaks_ties() {
        let topics = [
            img("/a/depth/image_raw"),
            img("/b/depth/image_raw"),
            img("/a/ir/image_raw"),
            img("/b/ir/image_raw"),
            info("/a/depth/camera_info"),
            info("/b/depth/camera_info"),
        ];
        let ov = TopicOverrides {
            depth: Some("/b/depth/image_raw".into()),
            ..Default::default()
        };
        let s = select_topics(&topics, &ov).unwrap();
        assert_eq!(s.ir, "/b/ir/image_raw");
        assert_eq!(s.info.as_deref(), Some("/b/depth/camera_info"));
        assert!(s.notes[0].contains("--depth-topic"));
        // An IR override picks the depth topic of its namespace.
        let ov = TopicOverrides {
            ir: Some("/a/ir/image_raw".into()),
            ..Default::default()
        };
        assert_eq!(select_topics(&topics, &ov).unwrap().depth, "/a/depth/image_raw");
        // Without overrides IR is ambiguous.
        assert!(matches!(select(&topics), Err(BagError::AmbiguousTopic { .. })));
    }

    #[test]
    fn info_rules() {
        let base = [img("/tof/depth/image_raw"), img("/tof/ir/image_raw")];
        let with = |extra: &[TopicInfo]| {
            let mut t = base.to_vec();
            t.extend_from_slice(extra);
            select(&t).map(|s| s.info)
        };
        assert_eq!(
            with(&[info("/tof/ir/camera_info"), info("/other/depth/camera_info")])
                .unwrap()
                .as_deref(),
            Some("/tof/ir/camera_info")
        );
        assert_eq!(
            with(&[info("/other/depth/camera_info")]).unwrap().as_deref(),
            Some("/other/depth/camera_info")
        );
        assert_eq!(with(&[info("/calib")]).unwrap().as_deref(), Some("/calib"));
        assert_eq!(with(&[info("/calib"), info("/calib2")]).unwrap(), None);
        assert!(matches!(
            with(&[info("/tof/ir/camera_info"), info("/tof/camera_info")]),
            Err(BagError::AmbiguousTopic {
                flag: "--info-topic",
                ..
            })
        ));
    }

    #[test]
    fn overrides_must_exist_with_the_right_type() {
        let topics = [
            img("/tof/depth/image_raw"),
            img("/tof/ir/image_raw"),
            info("/tof/depth/camera_info"),
        ];
        let ov = TopicOverrides {
            depth: Some("/nope".into()),
            ..Default::default()
        };
        let msg = select_topics(&topics, &ov).unwrap_err().to_string();
        assert!(
            msg.contains("--depth-topic /nope") && msg.contains("no such topic"),
            "{msg}"
        );
        assert!(msg.contains("/tof/ir/image_raw"), "{msg}");
        let ov = TopicOverrides {
            info: Some("/tof/ir/image_raw".into()),
            ..Default::default()
        };
        let msg = select_topics(&topics, &ov).unwrap_err().to_string();
        assert!(msg.contains("not sensor_msgs/msg/CameraInfo"), "{msg}");
        // A missing leading slash is forgiven.
        let ov = TopicOverrides {
            ir: Some("tof/ir/image_raw".into()),
            ..Default::default()
        };
        assert_eq!(select_topics(&topics, &ov).unwrap().ir, "/tof/ir/image_raw");
    }

    #[test]
    fn namespaces() {
        assert_eq!(camera_namespace("/tof/depth/image_raw"), "/tof");
        assert_eq!(camera_namespace("/tof/depth/camera_info"), "/tof");
        assert_eq!(camera_namespace("/cam/depth"), "/cam");
        assert_eq!(camera_namespace("/depth/image_raw"), "/");
        assert_eq!(camera_namespace("/tof/camera_info"), "/tof");
        assert_eq!(camera_namespace("/tof/ground_truth/depth"), "/tof");
        assert_eq!(camera_namespace("/cam/ir1/image_raw_x"), "/cam");
    }
}
