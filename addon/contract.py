"""The ONNX contract between training (which exports models) and the engine (which runs them).

Bump CONTRACT_VERSION when any of this changes; the engine refuses a model card whose contract it
does not know. training/ imports these names so the two sides cannot drift apart.
"""

CONTRACT_VERSION = "relight-onnx/1"
# Intrinsic models (addon/intrinsic.py renders their buffers): input ``image`` only, outputs the
# buffers below and ``parsing`` with the classes INTRINSIC_CLASSES.
INTRINSIC_CONTRACT = "relight-intrinsic/1"
KNOWN_CONTRACTS = (CONTRACT_VERSION, INTRINSIC_CONTRACT)

INPUT_IMAGE = "image"            # float32 [N, 3, H, W], linear Rec.709, normalised (normalise.py)
INPUT_LIGHT = "target_light"     # float32 [N, 3, 16, 16], light vector channels-first, unit power
OUTPUT_RELIT = "relit"           # float32 [N, 3, H, W], same units as the input image
OUTPUT_SOURCE_LIGHT = "source_light"  # float32 [N, 3, 16, 16], in the normalised image's units
OUTPUT_PARSING = "parsing"       # float32 [N, K, H, W] in [0, 1], one sigmoid per class
OUTPUT_NORMAL = "normal"         # intrinsic: float32 [N, 3, H, W] unit normals, camera frame
OUTPUT_HEIGHT = "height"         # intrinsic: float32 [N, 1, H, W] pixels toward the camera
OUTPUT_ALBEDO = "albedo"         # intrinsic: float32 [N, 3, H, W] albedo up to a gain per channel
# Optional for intrinsic models (a card lists it in "outputs" when its network has it): float32
# [N, 16, H, W], the light transport as order-3 SH (addon.intrinsic.TRANSFER_ORDER).
OUTPUT_TRANSFER = "transfer"
TRANSFER_CHANNELS = 16
# The transfer's coefficients odd in x (in the usual SH order): they change sign when the picture
# is mirrored left to right.
TRANSFER_X_ODD = (3, 4, 7, 10, 13, 15)
INTRINSIC_CLASSES = ("foreground", "skin")

# Parsing classes, in channel order. Channel 0 is the portrait foreground (the matte); the others
# are semantic regions (multi-label: each its own sigmoid). Models list theirs in the card.
PARSING_CLASSES = ("foreground", "skin", "hair", "brows", "eyes", "lips_mouth", "teeth", "neck",
                   "clothes")
FOREGROUND_CLASS = "foreground"

# Model card keys every card must have (models/<name>.json), as training/run/export.py and
# training/intrinsic/export.py write them.
REQUIRED_CARD_KEYS = ("contract", "name", "preset", "onnx", "sha256", "inputs", "outputs",
                      "stride", "working_size", "colour", "classes", "training", "metrics", "cost")

# Each contract's input and output names, in the order the cards list them.
INPUTS = {CONTRACT_VERSION: (INPUT_IMAGE, INPUT_LIGHT), INTRINSIC_CONTRACT: (INPUT_IMAGE,)}
OUTPUTS = {CONTRACT_VERSION: (OUTPUT_RELIT, OUTPUT_SOURCE_LIGHT, OUTPUT_PARSING),
           INTRINSIC_CONTRACT: (OUTPUT_NORMAL, OUTPUT_HEIGHT, OUTPUT_ALBEDO, OUTPUT_PARSING)}
# Outputs a model may list after those, in this order.
OPTIONAL_OUTPUTS = {CONTRACT_VERSION: (), INTRINSIC_CONTRACT: (OUTPUT_TRANSFER,)}

# CONTRACT_VERSION cards say how the relit output comes back to scene-linear radiance: by the
# target light's mean radiance k alone (addon/normalise.py), as "relit_scale": "k".
RELIT_SCALE = "k"
