

def test_orbax_save_waits_stay_off_the_console_and_other_warnings_on(tmp_path, caplog):
    from absl import logging as absl_logging

    from twinrl.learn.checkpoint import TrainStateCheckpointer

    TrainStateCheckpointer(tmp_path / "ckpt")
    with caplog.at_level("WARNING", logger="absl"):
        absl_logging.warning("Waiting for previous save to complete took %f seconds.", 5.0)
        absl_logging.warning("a warning of another kind")
    assert [r.getMessage() for r in caplog.records] == ["a warning of another kind"]
