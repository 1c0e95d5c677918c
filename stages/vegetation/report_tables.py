"""The report's tables of the composed world.usda: the forest by slope
class against the terrain's slope classes, and the plants per hectare on
the banks and elsewhere, read from the customData the instances layer
writes on /World/Vegetation (sites.forest_by_slope, sites.plants_on_banks).
Declared in STAGE.report (pipeline.contract.ReportTable)."""
from __future__ import annotations

from pathlib import Path

from pipeline.contract import Table

from .usd_layer import BANKS_KEY, FOREST_BY_SLOPE_KEY

VEGETATION_ROOT = "/World/Vegetation"


def forest_tables(world_usda: Path) -> tuple[Table, ...]:
    """The forest by slope class and the plants on the banks, from the
    composed world (none: the world has no vegetation layer)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(world_usda), Usd.Stage.LoadNone)
    prim = stage.GetPrimAtPath(VEGETATION_ROOT)
    if not prim.IsValid():
        return ()
    forest, banks = prim.GetCustomDataByKey(FOREST_BY_SLOPE_KEY), prim.GetCustomDataByKey(BANKS_KEY)
    return ((forest_table(dict(forest)),) if forest else ()) + ((banks_table(dict(banks)),) if banks else ())


def forest_table(data: dict) -> Table:
    """One row per slope class: its share of the land, of the trees and
    the trees per hectare."""
    rows = tuple((c, round(100.0 * float(land), 2), round(100.0 * float(tree), 2), round(float(per_ha), 1))
                 for c, land, tree, per_ha in zip(data["classes_deg"], data["land_share"], data["tree_share"],
                                                  data["trees_per_ha"]))
    return Table(("slope (deg)", "land %", "trees %", "trees per ha"), rows,
                 footer=("all", 100.0, 100.0, None), note=(
                     f"{int(data['trees'])} trees (instances of the species with tree = true) by the slope of their "
                     "terrain cell (the vegetation stage's attr.slope); land: the terrain cells outside water. "
                     "Closed forest rarely stands above 35-40 deg, scattered trees to about 45 deg, none above "
                     "50 deg."))


def banks_table(data: dict) -> Table:
    """Plants per hectare on the banks and elsewhere, per species."""
    rows = tuple((n, round(float(b), 1), round(float(e), 1))
                 for n, b, e in zip(data["species"], data["banks_per_ha"], data["elsewhere_per_ha"]))
    return Table(("species", "per ha on the banks", "per ha elsewhere"), rows, note=(
        f"banks: {float(data['bank_ha']):,.0f} ha of land with a riparian index of at least 0.5 (near rivers and "
        f"lakes and at most a few metres above them); elsewhere: {float(data['elsewhere_ha']):,.0f} ha."))
