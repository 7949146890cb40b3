"""The artifact catalog: every file and sub-folder a stage writes, named once."""

class Files:
    """The file names inside each stage's artifact, named once: the stages write them, and
    the library, ``cobgs export`` and the report read them from here (kedro's catalog idea:
    each artifact named in one place)."""

    DATASET = "dataset.json"  # dataset: the scene's typed record (cobgs.data.spec)
    SFM = "sfm.json"  # sfm: what SfM or triangulation did
    SFM_IMAGES = "images"  # sfm: the (undistorted) images
    SFM_MODEL = "sparse/0"  # sfm: the COLMAP model
    SFM_POINTS = "points.npz"  # sfm: points triangulated with known poses
    TRAIN = "train.json"  # train: config, schedule, views, held-out metrics, history
    SCENE_PLY = "scene.ply"  # train: the trained scene (standard 3DGS layout)
    MOMENTS = "adam_moments.pt"  # train: the Adam state (cobgs.train.adam_moments)
    RENDERS = "renders"  # train: held-out renders, <view>.png
    MASKS = "masks.json"  # masks: how the masks were made (<view>.png beside it)
    HELDOUT = "heldout.json"  # heldout: the ground-truth pictures written
    REFINE = "refine.json"  # refine: what the method did
    REFINED_PLY = "refined.ply"  # refine: the scene after the method, labels as extras
    SEGMENTATION = "segmentation.npz"  # refine: labels / foreground per Gaussian
    STAGE_SCORES = "stage_scores.npz"  # refine: per-stage scores
    RAEM_REMOVED = "raem_removed.ply"  # refine: what RAEM removed (restored for the scene render)
    SEGMENT = "segment.json"  # segment: counts, timings, views
    OBJECT_PLY = "object.ply"  # segment: the object alone
    BACKGROUND_PLY = "background.ply"  # segment: the scene without it
    PRED_MASKS = "pred_masks"  # segment: predicted masks, <view>.png
    PRED_VISIBLE = "pred_visible"  # segment: the object's visible mask (occluders rendered), <view>.png
    SCENE_RENDERS = "render"  # segment: the scene after the method, <view>.png
    BEFORE_RAEM_RENDERS = "render_before_raem"  # segment: the scene before RAEM's pruning, <view>.png
    OBJECT_RENDERS = "object"  # segment: the object alone, <view>.png
    REMOVED_RENDERS = "removed"  # segment: the scene without the object, <view>.png
    METRICS = "metrics.json"  # evaluate: the row and its details
    PER_VIEW = "per_view.csv"  # evaluate: one line per view
    SUMMARY = "summary.json"  # summary: every table
    SUMMARY_CSV = "summary.csv"  # summary: the rows
    BY_METHOD = "by_method.csv"
    BY_SCENE_METHOD = "by_scene_method.csv"
    TIMINGS = "timings.csv"
    SCENES = "scenes.csv"
    EXPORT_MARKER = "export.json"  # cobgs export: what was copied (pipeline.publish's marker)
    REPORT_MARKER = "report.json"  # cobgs report: the report's record (the same)

