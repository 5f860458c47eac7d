"""agvviz conventions — written once here, followed everywhere.

================  =======================================================================
topic             convention
================  =======================================================================
transforms        ``T_a_b`` (4×4, homogeneous) maps points from frame b into frame a:
                  ``p_a = T_a_b @ p_b``. It is b's pose expressed in a. Compose on the
                  shared inner frame: ``T_world_cam = T_world_agv @ T_agv_cam``.
world frame       right-handed, z up; the floor is the plane z = 0.
AGV body frame    ``agv``: x right, y forward, z up (paper 000 §5.2). Origin on the floor
                  under the vehicle centre.
camera frame      ``cam_<name>``: OpenCV — x right, y down, z forward (optical axis).
                  A ROS *optical* frame (``*_optical_frame``, REP 103/105: x right, y down,
                  z forward) is this convention already, so a camera's extrinsic is the
                  transform chain from the body frame to the frame id its images carry
                  (``base_link → camera_link → camera_optical_frame``), used as is; ROS
                  ``camera_link`` (x forward, y left, z up) is not an optical frame.
body frame        ``agv`` in agvviz recordings; in other logs a setting (``body_frame``,
                  default ``base_link``). ROS ``base_link`` is x forward, y left, z up
                  (REP 103), so heading/pitch/roll below, defined on the body's axes, differ
                  from a ROS yaw by the body's axis choice; errors between truth and estimate
                  of the same body are unaffected.
marker frame      origin at the code centre, z out of the printed face (towards a viewer),
                  x along the top edge (top-left → top-right), y from the bottom edge to
                  the top edge — OpenCV's ArUco / IPPE_SQUARE frame. A code of side s has
                  corners TL (-s/2, s/2, 0), TR (s/2, s/2, 0), BR (s/2, -s/2, 0),
                  BL (-s/2, -s/2, 0).
corner order      OpenCV ArUco order: top-left, top-right, bottom-right, bottom-left
                  (as printed). Optional edge midpoints follow in the order
                  top, right, bottom, left (paper 000 §6.2).
pixels            OpenCV: integer coordinates at pixel centres; an image's outer edge sits
                  at -0.5 and at width-0.5.
attitude          R = Rz(ψ)·Rx(θ)·Ry(γ): heading ψ, pitch θ, roll γ (paper 000 eq 38,
                  paper 002 eq 4). Heading 0 means the AGV's y axis points along world +y;
                  positive heading turns counter-clockwise seen from above. The gimbal-lock
                  rule of paper 000 eq 57 applies when |r32| > threshold (a setting).
tangent space     Lie algebra vectors are ordered ξ = (ρ, φ): translation part first,
                  rotation part second (paper 000 eqs 27–30).
perturbation      left: ``T ← Exp(δ) · T``. Jacobians are named ``J_out_wrt_in``; every
                  covariance states the tangent space it lives in (left, (ρ, φ) order).
units             SI, carried in names: ``_m``, ``_rad``, ``_deg``, ``_px``, ``_s``, ``_ns``.
time              integer nanoseconds (``log_time_ns``) in recordings and runs. A message's
                  time is its log time or its own header stamp (setting ``time_source``;
                  header for ROS logs, log time for agvviz recordings).
quaternions       (x, y, z, w) wherever a quaternion crosses a file boundary (Foxglove).
================  =======================================================================
"""

#: Default threshold T of paper 000 eq 57: |r32| > T is treated as pitch = ±π/2.
DEFAULT_GIMBAL_THRESHOLD = 0.999999

#: Frame names used in recordings and runs.
WORLD_FRAME = "world"
AGV_FRAME = "agv"


def camera_frame(cam_name: str) -> str:
    """Frame id of camera ``cam_name`` (``cam_<name>``)."""
    return f"cam_{cam_name}"
