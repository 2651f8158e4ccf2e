"""Annotations: the shared store, template re-detection and global alignment (Langlotz 2011
sec. 3.2, 4.2, 4.3). numpy / OpenCV / sqlite3 only; no rclpy."""
from .store import (Annotation, AnnotationStore, Landmark, SqliteAnnotationStore, StoreError,
                    open_store, validate_annotation, validate_landmark)

__all__ = ['Annotation', 'AnnotationStore', 'Landmark', 'SqliteAnnotationStore', 'StoreError',
           'open_store', 'validate_annotation', 'validate_landmark']
