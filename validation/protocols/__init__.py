"""The papers' protocols: functions that run the pipeline on phantoms and return tables of numbers.

* ``table2`` — Rhee Table 2: knee bent 10° by VBD, registered without initialisation;
* ``table3`` — Rhee Table 3: knee, 4 poses, template → 3 scans after VBD from estimated poses;
* ``table4`` — Rhee Table 4: hand, 10 poses, template → 9 scans after VBD from estimated poses;
* ``loo`` — leave one scan out: VBD vs EVD from the others' registrations (Rhee Figs. 11–12);
* ``eigenposes`` — principal components of a 71-pose hand library (Rhee §6.2);
* ``kurihara`` — Kurihara Eq. 1 joint centres of the CT hand in 5 poses;
* ``kurihara_skin`` — Kurihara §4–5: consistent skin meshes, SSD / PSD / WPSD, on the same study.

Each protocol is ``f(runner) -> Table`` (:class:`~validation.protocols.table.Table`).
The pipeline's stages live in the workbench, above this package, so a
protocol asks ``runner`` (supplied by :mod:`workbench.reproduce`) for what it
needs: ``study(name, phantom, *, settings, targets)`` → a
:class:`workbench.study.Study` on which ``targets`` (stage names) have run
(``phantom`` a dict of :class:`~validation.phantoms.PhantomSpec` fields,
``settings`` ``{stage: {setting: value}}``; the same arguments give the same
study); ``size`` (``"test"`` or ``"paper"``); ``seed`` (the phantoms');
``register_adaptive(study, scan_id, *, settings)`` → Rhee's Algorithm 1 on a
scan as the register stage runs ``method="adaptive"``, without changing the
study; ``with_peers`` (also run the general-purpose registrations); and
``say(message)``, a progress line.
"""

from __future__ import annotations

from .eigenposes import eigenposes
from .kurihara import kurihara
from .kurihara_skin import kurihara_skin
from .loo import loo
from .registration import table2, table3, table4
from .table import DEFINITIONS, Column, Table

__all__ = ["PROTOCOLS", "Table", "Column", "DEFINITIONS"]

PROTOCOLS = {
    "table2": table2,
    "table3": table3,
    "table4": table4,
    "loo": loo,
    "eigenposes": eigenposes,
    "kurihara": kurihara,
    "kurihara_skin": kurihara_skin,
}
