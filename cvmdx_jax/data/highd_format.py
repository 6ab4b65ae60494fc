"""The highD CSV format as the reader checks it: the columns of each file, the ones the
pipeline reads (`READ_COLUMNS`, checked strictly) and the ranges of their values
(`RANGES`); the rules are listed in `data.highd`'s docstring."""

from cvmdx_jax import constants

TRACKS_COLUMNS = (
    "frame",
    "id",
    "x",
    "y",
    "width",
    "height",
    "xVelocity",
    "yVelocity",
    "xAcceleration",
    "yAcceleration",
    "frontSightDistance",
    "backSightDistance",
    "dhw",
    "thw",
    "ttc",
    "precedingXVelocity",
    "precedingId",
    "followingId",
    "leftPrecedingId",
    "leftAlongsideId",
    "leftFollowingId",
    "rightPrecedingId",
    "rightAlongsideId",
    "rightFollowingId",
    "laneId",
)
TRACKS_META_COLUMNS = (
    "id",
    "width",
    "height",
    "initialFrame",
    "finalFrame",
    "numFrames",
    "class",
    "drivingDirection",
    "traveledDistance",
    "minXVelocity",
    "maxXVelocity",
    "meanXVelocity",
    "minDHW",
    "minTHW",
    "minTTC",
    "numLaneChanges",
)
RECORDING_META_COLUMNS = (
    "id",
    "frameRate",
    "locationId",
    "speedLimit",
    "month",
    "weekDay",
    "startTime",
    "duration",
    "totalDrivenDistance",
    "totalDrivenTime",
    "numVehicles",
    "numCars",
    "numTrucks",
    "upperLaneMarkings",
    "lowerLaneMarkings",
)
TEXT_COLUMNS = ("class", "month", "weekDay", "startTime", "upperLaneMarkings", "lowerLaneMarkings")
# Neighbour columns in `constants.VEHICLE_SLOTS[1:]` order.
NEIGHBOUR_COLUMNS = tuple(f"{slot}Id" for slot in constants.VEHICLE_SLOTS[1:])
COLUMNS = {
    "tracks": TRACKS_COLUMNS,
    "tracksMeta": TRACKS_META_COLUMNS,
    "recordingMeta": RECORDING_META_COLUMNS,
}
# The columns `read_recording` uses (checked strictly); the others only draw DataWarnings.
READ_COLUMNS = {
    # frame, id, the bounding box (x, y, width, height), xVelocity and yVelocity
    "tracks": (*TRACKS_COLUMNS[:8], "laneId", *NEIGHBOUR_COLUMNS),
    "tracksMeta": ("id", "initialFrame", "finalFrame", "numFrames", "drivingDirection"),
    "recordingMeta": ("frameRate", "upperLaneMarkings", "lowerLaneMarkings"),
}

ABSURD = 1e9  # bound on every numeric cell
MAX_ID = 1_000_000  # track ids index dense per-id arrays
MAX_FRAME = 10_000_000
POSITION, _LENGTH, _WIDTH = (-1e4, 1e4), (0.0, 50.0), (0.0, 10.0)
_ACCEL = (-20.0, 20.0)
# column -> (low, high, integer); a 0.0 low bound of a size is exclusive ("> 0"); outside
# READ_COLUMNS a value out of range is a warning.
RANGES = {
    "tracks": {
        "frame": (0, MAX_FRAME, True),
        "id": (1, MAX_ID, True),
        "x": (*POSITION, False),
        "y": (*POSITION, False),
        "width": (*_LENGTH, False),
        "height": (*_WIDTH, False),
        "xVelocity": (-100.0, 100.0, False),
        "yVelocity": (-20.0, 20.0, False),
        "xAcceleration": (*_ACCEL, False),
        "yAcceleration": (*_ACCEL, False),
        "laneId": (1, 100, True),
        **{c: (0, MAX_ID, True) for c in NEIGHBOUR_COLUMNS},
    },
    "tracksMeta": {
        "id": (1, MAX_ID, True),
        "width": (*_LENGTH, False),
        "height": (*_WIDTH, False),
        "initialFrame": (0, MAX_FRAME, True),
        "finalFrame": (0, MAX_FRAME, True),
        "numFrames": (1, MAX_FRAME, True),
        "drivingDirection": (1, 2, True),
    },
    "recordingMeta": {"frameRate": (1, 1000, True)},
}
SIZE_COLUMNS = ("width", "height")

# Bounds on a file before it is parsed (`data.highd_csv.scan`): far above any highD
# recording (recording 01's tracks file: 349 k rows of about 150 bytes, 52 MB; the largest
# are a few times that), far below what would exhaust memory.
MAX_FILE_BYTES = 1 << 30
MAX_LINE_BYTES = 1 << 16
MAX_ROWS = 4_000_000
