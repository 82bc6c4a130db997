"""Constants shared by every module: frame rate, audio rate, the SMPL-X skeleton.

World convention (see docs/representation.md): y up, metres, floor at y = 0, a person in the
rest pose faces +z. Everything that needs these numbers imports them from here.
"""

FPS = 30
FLOOR_HEIGHT = 0.0  # m: the floor's y in the world convention above
AUDIO_SAMPLE_RATE = 48_000
SAMPLES_PER_FRAME = AUDIO_SAMPLE_RATE // FPS  # 1600: Embody 3D's audio and motion are locked
NUM_BETAS = 300  # Embody 3D fits SMPL-X with 300 shape coefficients

SHARD_SCHEMA_VERSION = 2  # 2: each person's betas, rest joints and gender (docs/shard-format.md)
# Schema 1 shards lack only the body shape: they still train and generate; export asks for 2.
READABLE_SCHEMA_VERSIONS = (1, 2)

# The 55 joints of the SMPL-X kinematic tree, in the model file's order.
JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye_smplhf", "right_eye_smplhf",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2",
    "left_middle3", "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1",
    "left_ring2", "left_ring3", "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2",
    "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1",
    "right_ring2", "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3",
)
NUM_JOINTS = len(JOINT_NAMES)
BODY_JOINTS = 22  # pelvis .. right_wrist: the SMPL-X body, before the jaw, eyes and fingers

# Parent of each joint (-1 for the root), the SMPL-X kintree_table's first row.
JOINT_PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)

JOINT = {name: i for i, name in enumerate(JOINT_NAMES)}
NUM_VERTICES = 10_475
DEFAULT_SHELL_POINTS = 256

# Per-person SMPL-X parameter arrays as Embody 3D stores them: folder name -> width per frame.
SMPLX_PARAM_WIDTHS = {
    "smplx_mesh_betas": NUM_BETAS,
    "smplx_mesh_body_pose": 63,
    "smplx_mesh_global_orient": 3,
    "smplx_mesh_transl": 3,
    "smplx_mesh_left_hand_pose": 45,
    "smplx_mesh_right_hand_pose": 45,
}
