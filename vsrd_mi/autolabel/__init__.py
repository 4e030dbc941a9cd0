"""The autolabeling job: one target frame end to end (:mod:`.job`) with its ``--vis`` figures
(:mod:`.visualise`), the consensus of parked cars over a sequence (:mod:`.consensus`) and
``vsrd-mi autolabel`` (:mod:`.cli`)."""
