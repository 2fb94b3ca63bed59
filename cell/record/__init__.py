"""The record of a job: its folder and journal (:mod:`~cell.record.jobfolder`), the MCAP run log
(:mod:`~cell.record.runlog`), the archive and its index (:mod:`~cell.record.archive`) and the
inspection report (:mod:`~cell.record.report`)."""
