"""The four papers jaxdrive implements, with the arXiv version every equation number refers to.

Docstrings cite a formula as ``MiLA [2503.15875v1] eq. 13``: the identifier pins the version,
because equation, section and table numbers move between versions of a preprint.
``tests/test_references.py`` checks that every equation citation of these papers carries it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Paper:
    name: str  # how the code and docs call it
    title: str
    authors: str
    arxiv: str  # identifier with its version, e.g. "2503.15875v1"

    @property
    def url(self) -> str:
        return f"https://arxiv.org/abs/{self.arxiv}"

    def cite(self, where: str = "") -> str:
        """``"MiLA [2503.15875v1]"``, or with ``where`` (``"eq. 13"``) appended."""
        return f"{self.name} [{self.arxiv}]" + (f" {where}" if where else "")


PAPERS: dict[str, Paper] = {
    p.name: p
    for p in (
        Paper(
            "MiLA",
            "MiLA: Multi-view Intensive-fidelity Long-term Video Generation World Model for Autonomous Driving",
            "Haiguang Wang, Daqi Liu, Hongwei Xie, Haisong Liu, Enhui Ma, Kaicheng Yu, Limin Wang, Bing Wang",
            "2503.15875v1",
        ),
        Paper(
            "LongDWM",
            "LongDWM: Cross-Granularity Distillation for Building a Long-Term Driving World Model",
            "Xiaodong Wang, Zhirong Wu, Peixi Peng",
            "2506.01546v1",
        ),
        Paper(
            "STAGE",
            "STAGE: A Stream-Centric Generative World Model for Long-Horizon Driving-Scene Simulation",
            "Jiamin Wang, Yichen Yao, Xiang Feng, Hang Wu, Yaming Wang, Qingqiu Huang, Yuexin Ma, Xinge Zhu",
            "2506.13138v1",
        ),
        Paper(
            "MagicDrive-V2",
            "MagicDrive-V2: High-Resolution Long Video Generation for Autonomous Driving with Adaptive Control",
            "Ruiyuan Gao, Kai Chen, Bo Xiao, Lanqing Hong, Zhenguo Li, Qiang Xu",
            "2411.13807v3",
        ),
    )
}


def paper(name: str) -> Paper:
    """The paper called ``name`` (``"MiLA"``, ``"LongDWM"``, ``"STAGE"``, ``"MagicDrive-V2"``)."""
    if name not in PAPERS:
        raise ValueError(f"name: expected one of {', '.join(PAPERS)}, got {name!r}")
    return PAPERS[name]
