"""The run: driving a run or an offline fit on a machine. Its settings resolved in one place
(`settings.py`), a resume's config.json read once (`resume.py`), the run loop (`loop.py`: epochs,
checkpoints, logs, reports, resume), its folder (`rundir`), `checkpoint`, `console`,
`provenance`, the reconstruction figures drawn during a run or from a checkpoint (`recon`), and
the offline fit's driver (`offline`).

Imports `bulbjax.config`, the faces of `bulbjax.epoch` and `bulbjax.report`, and the layers below;
the command line (`bulbjax.cli`, `bulbjax.run_command`) and `bulbjax.reproduce` use this face."""

from bulbjax.run.console import StageLog, log_to_file, process_start_time
from bulbjax.run.loop import RunResult, run
from bulbjax.run.offline import fit
from bulbjax.run.recon import RunFigures, redraw_figures
from bulbjax.run.resume import Resume, SavedRun, check_resume
from bulbjax.run.rundir import LOG_FILE, RunFolderExists, check_out_dir, checkpoint_steps, log_name
from bulbjax.run.settings import parse_version, resolve, resolve_offline, resolve_resume, resolve_run

__all__ = ["StageLog", "log_to_file", "process_start_time", "RunResult", "run", "fit", "RunFigures", "redraw_figures",
           "Resume", "SavedRun", "check_resume", "LOG_FILE", "RunFolderExists", "check_out_dir", "checkpoint_steps",
           "log_name", "parse_version", "resolve", "resolve_offline", "resolve_resume", "resolve_run"]
