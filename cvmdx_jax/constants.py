"""Fixed numbers of the cVMD/cVMDx data contract (paper and reference code)."""

FRAME_RATE_HZ = 25
DT = 1.0 / FRAME_RATE_HZ  # s per step
T_OBS = 75  # observed steps (3 s)
T_PRED = 125  # predicted steps (5 s)
NUM_VEHICLES = 9  # ego + 8 neighbours
NUM_FEATURES = 4  # x, y, v_x, v_y
NUM_CLASSES = 3  # 0 keep lane, 1 lane change right, 2 lane change left

# Slot order of the 9 vehicles (cVMD `.mat` data_keys).
VEHICLE_SLOTS = (
    "ego",
    "following",
    "preceding",
    "leftPreceding",
    "leftAlongside",
    "leftFollowing",
    "rightPreceding",
    "rightAlongside",
    "rightFollowing",
)
CLASS_NAMES = ("kl", "lcr", "lcl")

# Control normalisation: a_x / 4 m/s^2, yaw rate / 0.7 rad/s, clipped to [-1, 1].
ACCEL_SCALE = 4.0  # m/s^2
YAW_RATE_SCALE = 0.7  # rad/s

# Precision of the matrix products outside the networks' layers (the nearest-codebook search,
# the Mahalanobis delta, VMM fit, PCA, GMM, k-means, hypothesis means, scores): true float32
# on every backend. By default XLA computes float32 products on
# NVIDIA GPUs in TF32 (10-bit mantissa), which moved hypothesis positions 100-290 m ahead by
# up to 12 cm on an H200 (BUILD_NOTES, 2026-12-04). CPUs compute float32 either way: CPU
# outputs are unchanged.
# The networks keep the backend's default (a GPU's TF32 convolutions, as PyTorch's cuDNN uses).
EXACT_MATMUL = "highest"
