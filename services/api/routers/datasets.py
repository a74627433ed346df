"""Datasets: the motion libraries a spec may name."""

from __future__ import annotations

import re

from fastapi import APIRouter, Depends
from sqlalchemy.orm import Session

from services import jobs
from services.api.deps import get_db, get_graphstore, get_tenant
from services.api.routers.jobs import PROBLEM
from services.api.schemas import DatasetList, DatasetOut
from services.common import catalog
from services.common.problems import ApiError
from services.models import Dataset, Tenant

DATASET_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")  # as Spec.dataset

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


def _out(row: Dataset) -> DatasetOut:
    return DatasetOut(
        name=row.name,
        version=row.version,
        licence=row.licence,
        embedding=row.embedding,
        stats=row.stats or {},
        created_at=row.created_at,
    )


@router.get(
    "", response_model=DatasetList, summary="Datasets with a built graph", responses={401: PROBLEM}
)
def list_datasets(
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    graphstore=Depends(get_graphstore),
):
    catalog.refresh_catalog(db, graphstore)
    return DatasetList(items=[_out(r) for r in jobs.list_datasets(db)])


@router.get(
    "/{name}",
    response_model=DatasetOut,
    summary="One dataset",
    responses={401: PROBLEM, 404: PROBLEM},
)
def get_dataset(
    name: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    graphstore=Depends(get_graphstore),
):
    row = catalog.find_dataset(db, name, graphstore) if DATASET_NAME.match(name) else None
    if row is None:
        raise ApiError(404, "unknown_dataset", f"no dataset named {name!r}", field="name")
    return _out(row)
