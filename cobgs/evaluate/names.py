"""The names of the numbers a result row averages, in a module that imports nothing (the summary
stage reads it without numpy: a cached run imports no numerical library)."""

#: The numbers of a result row that are averaged (over objects within a scene, then over scenes):
#: the summary stage's tables and the report's (which adds the refinement's counts and times) read
#: this, the one list (also :data:`cobgs.evaluate.protocols.METRICS`).
METRICS = ("iou", "acc", "biou", "iou_released", "acc_released", "biou_released", "iou_occlusion", "acc_occlusion",
           "biou_occlusion", "psnr", "psnr_before_raem", "psnr_vanilla", "psnr_delta", "psnr_delta_before_raem",
           "num_gaussians", "object_gaussians")
