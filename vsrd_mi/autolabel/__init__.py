"""The autolabeling job: one target frame end to end (:mod:`.job`), the consensus of parked cars
over a sequence (:mod:`.consensus`) and ``vsrd-mi autolabel`` (:mod:`.cli`)."""
