"""The `export`, `update` and `check` sections: bundles and a site that changes."""

from __future__ import annotations

from pydantic import Field

from pipeline.config.base import Strict
from pipeline.config.site import MappingConfig


class ExportConfig(Strict):
    """`siteloc export`: the deployable bundle."""

    version: str = Field("0.1.0", pattern=r"^[0-9A-Za-z][0-9A-Za-z.+_-]*$",
                         description="bundle version: the directory is bundles/<site>-<version>")
    parity_images: int = Field(4, ge=1, description="site images on which the ONNX detector is checked against torch")
    archive: bool = Field(True, description="also write <site>-<version>.tar.gz beside the directory")


class UpdateConfig(Strict):
    """`siteloc update`: new captures of changed areas merged into a site database (docs/update.md)."""

    proximity_m: float = Field(2.0, gt=0, description="a new stop without room/area labels belongs to the area of "
                               "the nearest old stop within this many metres (or replaces that stop when it has "
                               "no labels either)")
    mapping: MappingConfig = Field(MappingConfig(), description="how the new runs' scans are mapped to patch the "
                                   "changed areas (the resolution is always the site map's)")
    map_tolerance_m: float = Field(0.1, ge=0, description="a wall the new scans see within this of a wall the map "
                                   "has is the same wall: only obstacles and free space farther than this from what "
                                   "the map says change it (and cells the map did not know)")


class CheckConfig(Strict):
    """`siteloc check`: how well a bundle fits the building as it is now (docs/update.md#siteloc-check)."""

    position_m: float = Field(2.0, gt=0, description="a retrieved pose is right within this many metres ...")
    heading_deg: float = Field(30.0, gt=0, le=180, description="... and this heading of the image's pose")
    max_recall_drop: float = Field(0.25, gt=0, le=1, description="re-capture an area whose recall@4 falls this much "
                                   "under the bundle's baseline (the area's own, else the whole site's)")
    same_place_m: float = Field(0.3, gt=0, description="a database view within this many metres ...")
    same_place_deg: float = Field(15.0, gt=0, le=180, description="... and degrees of a new image shows its place")
    min_place_likeness: float = Field(0.8, ge=0, le=1, description="a new view is changed when it looks like the "
                                      "bundle's at the same place less than this: 1 unchanged, 0 no closer than a "
                                      "neighbouring stop's view (the baseline's neighbour similarity)")
    max_changed_views: float = Field(0.2, gt=0, le=1, description="... and an area is re-captured when more than "
                                     "this share of its new same-place views changed")
    max_map_drop: float = Field(0.15, gt=0, le=1, description="retrain the detector when its mAP@0.5 on the new "
                                "images falls this much under the baseline's")
    endpoint_tolerance_m: float = Field(0.1, ge=0, description="a scan endpoint within this of an occupied map "
                                        "cell agrees with the map")
    min_endpoint_share: float = Field(0.85, gt=0, le=1, description="update the map of an area whose new scan "
                                      "endpoints agree with it less often than this ...")
    map_change_m2: float = Field(0.25, ge=0, description="... or where the new scans see more than this many square "
                                 "metres of new obstacles or of walls gone")
    min_area_images: int = Field(6, ge=1, description="an area with fewer new images gets figures but no verdict")
    min_area_endpoints: int = Field(200, ge=1, description="an area with fewer new scan endpoints: no map verdict")
