"""Execute notebooks/neural.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook

# Both variants and the learning curve run on the embedded records as in the notebook;
# only the training is shorter (the notebook's time is mostly compilation).
SMALL_TRAINING = {
    "n_synthetic": 400,
    "pretrain_epochs": 10,
    "steps_per_epoch": 4,
    "batch_size": 64,
    "finetune_epochs": 100,
    "residual_epochs": 150,
}


def test_notebook_neural_runs(tmp_path, monkeypatch):
    _, text, _ = run_notebook("neural.ipynb", tmp_path, monkeypatch, overrides={"nn_settings": SMALL_TRAINING})
    assert "fleet held-out median LM+residual" in text
    assert "networks without the fallback rule" in text
    assert "notebook ran in" in text
