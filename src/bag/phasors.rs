//! Multi-frequency input in bags (docs/interfaces.md, "Multi-frequency
//! input"): one `32FC2` image per modulation frequency on
//! `phasor_<k>/image_raw` (k = 0, 1, ...) beside the depth image, and the
//! frequencies in an MCAP metadata record named [`METADATA_NAME`] under the
//! key [`FREQUENCIES_KEY`].

use std::collections::{BTreeMap, BTreeSet};

use super::discover::camera_namespace;
use super::reader::BagMetadata;
use super::{normalize_type_name, BagError, TopicInfo};

/// The name of the metadata record this package writes into its bags.
pub const METADATA_NAME: &str = "translucent_tof";

/// The key of the modulation frequencies in [`METADATA_NAME`]'s record: the
/// frequencies in hertz, in the order of `k`, comma-separated (`20000000,50000000,100000000`).
pub const FREQUENCIES_KEY: &str = "modulation_frequencies_hz";

/// `phasor_<k>/image_raw` under `namespace` (`/tof` gives `/tof/phasor_0/image_raw`).
pub fn phasor_topic(namespace: &str, k: usize) -> String {
    format!("{}/phasor_{k}/image_raw", namespace.trim_end_matches('/'))
}

/// The metadata pairs recording `frequencies_hz`.
pub fn frequencies_metadata(frequencies_hz: &[f64]) -> BTreeMap<String, String> {
    let text: Vec<String> = frequencies_hz.iter().map(|f| f.to_string()).collect();
    BTreeMap::from([(FREQUENCIES_KEY.to_string(), text.join(","))])
}

fn bad(what: String) -> BagError {
    BagError::MultiFrequency(what)
}

/// Frequencies as [`frequencies_metadata`] writes them: comma-separated
/// positive hertz (whitespace allowed).
pub fn parse_frequencies(text: &str) -> Result<Vec<f64>, BagError> {
    text.split(',')
        .map(|v| match v.trim().parse::<f64>() {
            Ok(f) if f.is_finite() && f > 0.0 => Ok(f),
            _ => Err(bad(format!(
                "metadata {METADATA_NAME}.{FREQUENCIES_KEY} = {text:?}: {:?} is not a positive frequency in Hz",
                v.trim()
            ))),
        })
        .collect()
}

/// The frequencies recorded in a bag's metadata; `None` when it records none.
pub fn recorded_frequencies(metadata: &[BagMetadata]) -> Result<Option<Vec<f64>>, BagError> {
    let found = metadata
        .iter()
        .filter(|m| m.name == METADATA_NAME)
        .find_map(|m| m.entries.get(FREQUENCIES_KEY));
    found.map(|text| parse_frequencies(text)).transpose()
}

/// `k` of a topic named `.../phasor_<k>/image_raw`, and the namespace before it.
fn phasor_index(topic: &str) -> Option<(String, usize)> {
    let rest = topic.strip_suffix("/image_raw")?;
    let (ns, leaf) = rest.rsplit_once('/').unwrap_or(("", rest));
    let k = leaf.strip_prefix("phasor_")?;
    if k.is_empty() || !k.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((format!("/{}", ns.trim_start_matches('/')), k.parse().ok()?))
}

/// The phasor topics of the depth topic's camera (`phasor_0/image_raw`,
/// `phasor_1/image_raw`, ... of `sensor_msgs/msg/Image` in its namespace;
/// else those of the only namespace that has any), in the order of `k`.
/// Empty when the bag has none. A gap in `k` is an error.
pub fn phasor_topics(topics: &[TopicInfo], depth_topic: &str) -> Result<Vec<String>, BagError> {
    let mut by_ns: BTreeMap<String, BTreeMap<usize, String>> = BTreeMap::new();
    for t in topics {
        if normalize_type_name(&t.type_name) != "sensor_msgs/msg/Image" {
            continue;
        }
        if let Some((ns, k)) = phasor_index(&t.name) {
            by_ns.entry(ns).or_default().insert(k, t.name.clone());
        }
    }
    let ns = camera_namespace(depth_topic);
    let chosen = match by_ns.remove(&ns) {
        Some(set) => set,
        None if by_ns.len() <= 1 => by_ns.into_values().next().unwrap_or_default(),
        None => {
            let spaces: BTreeSet<String> = by_ns.into_keys().collect();
            return Err(bad(format!(
                "phasor topics in several namespaces ({}) and none in the depth topic's ({ns})",
                spaces.into_iter().collect::<Vec<_>>().join(", ")
            )));
        }
    };
    if let Some(gap) = (0..chosen.len()).find(|k| !chosen.contains_key(k)) {
        let have: Vec<String> = chosen.values().cloned().collect();
        return Err(bad(format!(
            "phasor topics {} skip phasor_{gap}: k must run 0, 1, ... without a gap",
            have.join(", ")
        )));
    }
    Ok(chosen.into_values().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image_topic(name: &str) -> TopicInfo {
        TopicInfo {
            name: name.into(),
            type_name: "sensor_msgs/msg/Image".into(),
            message_count: 1,
        }
    }

    #[test]
    fn frequencies_round_trip_through_metadata() {
        let f = [20e6, 50e6, 100e6];
        let pairs = frequencies_metadata(&f);
        assert_eq!(pairs[FREQUENCIES_KEY], "20000000,50000000,100000000");
        let records = vec![
            BagMetadata {
                name: "other".to_string(),
                entries: BTreeMap::new(),
            },
            BagMetadata {
                name: METADATA_NAME.to_string(),
                entries: pairs,
            },
        ];
        assert_eq!(recorded_frequencies(&records).unwrap(), Some(f.to_vec()));
        assert_eq!(recorded_frequencies(&records[..1]).unwrap(), None);
        assert_eq!(parse_frequencies(" 2e7, 1e8 ").unwrap(), [2e7, 1e8]);
        for bad in ["", "20e6,,50e6", "20e6,-1", "x", "inf"] {
            let e = parse_frequencies(bad).unwrap_err().to_string();
            assert!(e.contains("not a positive frequency"), "{bad}: {e}");
        }
    }

    #[test]
    fn phasor_topics_are_found_beside_the_depth_in_order() {
        let topics: Vec<TopicInfo> = [
            "/tof/depth/image_raw",
            "/tof/phasor_1/image_raw",
            "/tof/phasor_0/image_raw",
            "/tof/phasor_2/image_raw",
            "/other/phasor_0/image_raw",
            "/tof/phasor_x/image_raw",
        ]
        .into_iter()
        .map(image_topic)
        .collect();
        assert_eq!(
            phasor_topics(&topics, "/tof/depth/image_raw").unwrap(),
            [
                "/tof/phasor_0/image_raw",
                "/tof/phasor_1/image_raw",
                "/tof/phasor_2/image_raw"
            ]
        );
        assert_eq!(phasor_topic("/tof/", 2), "/tof/phasor_2/image_raw");
        // None: single frequency.
        assert!(phasor_topics(&topics[..1], "/tof/depth/image_raw").unwrap().is_empty());
        // A gap.
        let gap = [
            image_topic("/tof/phasor_0/image_raw"),
            image_topic("/tof/phasor_2/image_raw"),
        ];
        let e = phasor_topics(&gap, "/tof/depth/image_raw").unwrap_err().to_string();
        assert!(e.contains("skip phasor_1"), "{e}");
        // Another type is not a phasor image.
        let info = TopicInfo {
            type_name: "sensor_msgs/msg/CameraInfo".into(),
            ..image_topic("/tof/phasor_0/image_raw")
        };
        assert!(phasor_topics(&[info], "/tof/depth/image_raw").unwrap().is_empty());
    }
}
