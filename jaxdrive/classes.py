"""The class vocabularies of jaxdrive's driving controls: the object classes of boxes and the road
classes of BEV maps.

One home below both of their readers: the clip record (:mod:`jaxdrive.data.schema`, which
re-exports them) and the models that take or give classes (the future-controls predictor,
:mod:`jaxdrive.models.predictor`; the segmentation evaluator, :mod:`jaxdrive.models.segmenter`),
so that neither layer imports the other for them.
"""

# MagicDrive-V2's 10 object classes (the nuScenes detection classes); class id = index.
OBJECT_CLASSES = (
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "barrier",
    "motorcycle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
)

# MagicDrive's 8 BEV road classes, the channel order of ``bev_map``.
BEV_CLASSES = (
    "drivable_area",
    "ped_crossing",
    "walkway",
    "stop_line",
    "carpark_area",
    "road_divider",
    "lane_divider",
    "road_block",
)
