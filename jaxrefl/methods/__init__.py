"""The estimators: Method I (`local`), Method II (`radiosity`), Method III (`inverse_photon`,
with `photon`, `gather`, `final_gather`) and `auto`."""
