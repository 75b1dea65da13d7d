"""profile_pose_ros: 6-DoF pose from one laser profile of a faceted gauge (Chen & Lin, RA-L 2026)."""
