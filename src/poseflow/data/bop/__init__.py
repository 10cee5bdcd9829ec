"""Read and write datasets in the BOP format (LM-O, TUD-L, IC-BIN, YCB-V, ...).

A BOP dataset is a folder ``root`` holding ``models/`` and ``models_eval/`` (PLY meshes in mm
and ``models_info.json``), the split folders (``test``, ``train_pbr``, ``test_primesense``, ...)
with one folder per scene ``{scene_id:06d}``, and optionally ``test_targets_bop19.json``. A scene
folder holds ``scene_camera.json``, ``scene_gt.json``, ``scene_gt_info.json``, ``rgb/`` (or
``gray/``), ``depth/``, ``mask/`` and ``mask_visib/``.

Units: everything returned by this module is in **metres** (depth maps, translations, diameters,
symmetry offsets); the files are in millimetres and are converted here, on read and on write.
Poses are ``(4, 4)`` model-to-camera transforms, ``x_cam = R x_model + t``. Pixel coordinates
follow the BOP/OpenCV convention: pixel ``(u, v)`` is column ``u``, row ``v`` and ``K`` maps camera
points to those integer pixel positions.

Three levels of lazy, indexable access, all usable with a :class:`torch.utils.data.DataLoader`:

- :class:`BOPScene`: the images of one scene (``scene[i]`` is an image sample);
- :class:`BOPImageDataset`: every image of a split (batch with :func:`collate_images`, which pads
  the variable number of instances);
- :class:`BOPInstanceDataset` (ground-truth instances) and :class:`BOPDetectionDataset`
  (instances given by detection/segmentation results such as the public ZebraPose masks): one
  object instance per item, collated by the default collate function.

Problems confined to one instance (an empty mask, fewer than ``min_valid_pixels`` valid depth
pixels inside the mask, NaN or zero depth) never raise: the sample's ``valid`` flag is False and a
:class:`BOPDataWarning` names the scene, image and instance, so that an evaluation loop can skip it.
Problems of the files themselves (missing files or keys, a depth map clearly stored in metres
although ``depth_scale`` declares millimetres) raise :class:`BOPFormatError` or
:class:`MissingFileError` naming the file, scene and image.
"""

from poseflow.data.bop import datasets, images, json_io, records, writer
from poseflow.data.bop.datasets import *  # noqa: F403
from poseflow.data.bop.images import *  # noqa: F403
from poseflow.data.bop.json_io import *  # noqa: F403
from poseflow.data.bop.records import *  # noqa: F403
from poseflow.data.bop.writer import *  # noqa: F403
from poseflow.errors import BOPFormatError, MissingFileError

# Every module's public names, and the two errors its readers raise.
__all__ = ["BOPFormatError", "MissingFileError"]
__all__ += records.__all__
__all__ += json_io.__all__
__all__ += images.__all__
__all__ += datasets.__all__
__all__ += writer.__all__
