//! `translucent_tof_msgs/msg/*`: this package's own messages (`msg/`, built for
//! ROS 2 by the ament package `ros/translucent_tof_msgs`).

use serde::{Deserialize, Serialize};

use super::std_msgs::Header;
use super::RosMessage;

/// The ROS 2 package of this crate's messages (`ros/translucent_tof_msgs`): their
/// type names are `translucent_tof_msgs/msg/NAME`, on DDS
/// `translucent_tof_msgs::msg::dds_::NAME_`.
pub const PACKAGE: &str = "translucent_tof_msgs";

/// `translucent_tof_msgs/msg/TranslucencyEstimate` (field order = `msg/TranslucencyEstimate.msg`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TranslucencyEstimate {
    /// Stamp of the frame the estimate was used for.
    pub header: Header,
    /// Translucency, 0 opaque .. 1 fully transmissive.
    pub xi: f64,
    /// Lower end of the interval the data support.
    pub xi_lower: f64,
    /// Upper end.
    pub xi_upper: f64,
    /// `fixed`, `calibrated`, `one_material` or `eq12_residual`.
    pub method: String,
    /// Pixels segmented as translucent in the frame.
    pub translucent_pixels: u32,
    /// RMS of the model's residual over those pixels, mm.
    pub fit_residual_mm: f64,
    /// Frames the estimate pools.
    pub frames_pooled: u32,
    /// The region's material (stable over frames while it is kept); 0: one ξ for the frame.
    pub region_id: u32,
    /// Pixels of this region in the frame.
    pub region_pixels: u32,
    /// The data say this region is opaque: its depth is kept and it is not in the mask.
    pub opaque: bool,
    /// With a materials file: the object's class (a known material's name, `opaque` or
    /// `unknown`); empty without one.
    pub material: String,
    /// The posterior probability of that class (NaN without a materials file).
    pub class_probability: f64,
}

impl RosMessage for TranslucencyEstimate {
    const TYPE_NAME: &'static str = "translucent_tof_msgs/msg/TranslucencyEstimate";
    fn definition() -> &'static str {
        include_str!("../../msg/TranslucencyEstimate.msg")
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        let mut deps = vec![(Header::TYPE_NAME, Header::definition())];
        deps.extend(Header::dependencies());
        deps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{from_cdr, ros2msg_schema, to_cdr};

    #[test]
    fn round_trips_and_schema_names_header_and_time() {
        let m = TranslucencyEstimate {
            header: Header::new(1_700_000_000_123_456_789, "tof_optical_frame"),
            xi: 0.65,
            xi_lower: 0.63,
            xi_upper: 0.67,
            method: "one_material".into(),
            translucent_pixels: 1234,
            fit_residual_mm: 0.5,
            frames_pooled: 8,
            region_id: 2,
            region_pixels: 900,
            opaque: false,
            material: "folder".into(),
            class_probability: 0.93,
        };
        let back: TranslucencyEstimate = from_cdr(&to_cdr(&m).unwrap()).unwrap();
        assert_eq!(back, m);
        let schema = ros2msg_schema::<TranslucencyEstimate>();
        assert!(schema.contains("MSG: std_msgs/Header") && schema.contains("MSG: builtin_interfaces/Time"));
    }

    /// The type name is the one the ament package builds (`ros/translucent_tof_msgs`),
    /// in bags and on DDS, and that package's definition is this one.
    #[test]
    fn type_name_is_the_ament_packages() {
        let package_xml = include_str!("../../ros/translucent_tof_msgs/package.xml");
        assert!(
            package_xml.contains(&format!("<name>{PACKAGE}</name>")),
            "{package_xml}"
        );
        assert_eq!(
            TranslucencyEstimate::TYPE_NAME,
            format!("{PACKAGE}/msg/TranslucencyEstimate")
        );
        assert_eq!(
            ros2_client::MessageTypeName::new(PACKAGE, "TranslucencyEstimate").dds_msg_type(),
            "translucent_tof_msgs::msg::dds_::TranslucencyEstimate_"
        );
        assert_eq!(
            TranslucencyEstimate::definition(),
            include_str!("../../ros/translucent_tof_msgs/msg/TranslucencyEstimate.msg")
        );
    }
}
