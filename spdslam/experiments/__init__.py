"""Experiments: the paper's simulation study (Table II, Fig. 12) as batched solves, its
summaries beside the paper's numbers, its files, and an independent reference solver
(SciPy's trust-region least squares on the same trials and residuals), and the engines
that run independent tasks here or on a Ray cluster: sharded studies and batches of sequence
runs (manifests). Imports ``geometry``, ``factors``,
``solver``, ``synthetic``, ``io``, ``mapping`` and ``evaluation``.
"""

from ._batch import BATCH_COLUMNS as BATCH_COLUMNS
from ._batch import JOB_SETTINGS as JOB_SETTINGS
from ._batch import Job as Job
from ._batch import JobReport as JobReport
from ._batch import map_sequence as map_sequence
from ._batch import read_manifest as read_manifest
from ._batch import run_batch as run_batch
from ._batch import write_batch_report as write_batch_report
from ._engines import RAY_MISSING as RAY_MISSING
from ._engines import LocalEngine as LocalEngine
from ._engines import RayEngine as RayEngine
from ._engines import TaskOutcome as TaskOutcome
from ._engines import make_engine as make_engine
from ._figures import LATENCY_COLUMNS as LATENCY_COLUMNS
from ._figures import image_for as image_for
from ._figures import latency_csv as latency_csv
from ._figures import plot_latency as plot_latency
from ._figures import plot_map_top as plot_map_top
from ._figures import plot_overlay as plot_overlay
from ._figures import write_overlays as write_overlays
from ._localize import localize_sequence as localize_sequence
from ._localize import merge_recordings as merge_recordings
from ._outputs import plot_convergence as plot_convergence
from ._outputs import write_outputs as write_outputs
from ._paper import MODEL_NAMES as MODEL_NAMES
from ._paper import PAPER_IOU_H as PAPER_IOU_H
from ._paper import PAPER_SUCCESS as PAPER_SUCCESS
from ._paper import PAPER_SUCCESS_IOU as PAPER_SUCCESS_IOU
from ._paper import PARAM_NAMES as PARAM_NAMES
from ._recording import RERUN_MISSING as RERUN_MISSING
from ._recording import projected_ellipses as projected_ellipses
from ._recording import write_recording as write_recording  # needs rerun-sdk (the viewer extra) when called
from ._reference import compare_with_reference as compare_with_reference
from ._reference import reference_solve as reference_solve
from ._reference import reference_table as reference_table
from ._run_folder import association_record as association_record
from ._run_folder import frame_rate as frame_rate
from ._run_folder import write_run as write_run
from ._study import StudyConfig as StudyConfig
from ._study import StudyResult as StudyResult
from ._study import run_study as run_study
from ._summary import COLLAPSED_RATIO as COLLAPSED_RATIO
from ._summary import CSV_COLUMNS as CSV_COLUMNS
from ._summary import pooled_success_iou as pooled_success_iou
from ._summary import summarize as summarize
from ._summary import table_markdown as table_markdown
