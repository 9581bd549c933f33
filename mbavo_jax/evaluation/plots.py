"""PNG plots (matplotlib, Agg): trajectory top view with ground truth, error over time."""

from __future__ import annotations

import pathlib

import numpy as np

__all__ = ["plot_trajectories", "plot_error_over_time"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(path, ref_xyz: np.ndarray, est_xyz: np.ndarray, title: str = "", plane: str = "xz") -> None:
    """Top view (default x-z: the camera's forward plane) of reference and aligned estimate."""
    plt = _plt()
    a, b = "xyz".index(plane[0]), "xyz".index(plane[1])
    fig, ax = plt.subplots(figsize=(6, 5), dpi=100)
    ax.plot(ref_xyz[:, a], ref_xyz[:, b], "k-", lw=1.5, label="ground truth")
    ax.plot(est_xyz[:, a], est_xyz[:, b], "C1-", lw=1.2, label="estimate (aligned)")
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(pathlib.Path(path))
    plt.close(fig)


def plot_error_over_time(path, stamps: np.ndarray, errors: np.ndarray, title: str = "", ylabel: str = "APE [m]") -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3), dpi=100)
    ax.plot(stamps - stamps[0], errors, "C0-")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(pathlib.Path(path))
    plt.close(fig)
