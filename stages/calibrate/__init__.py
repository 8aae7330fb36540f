"""Camera calibration from ChArUco board takes: detection, intrinsics, extrinsics, bundle adjustment."""
