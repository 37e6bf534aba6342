// Fluidd's own store code in a real Vuex store, fed as Fluidd feeds it.  Registered: printer
// (state.printer holds Klipper's objects), files (the printing file's Moonraker metadata, which
// getPrinterFile reads), history (the job a file's job_id names: Fluidd's "actual" time), and
// config (uiSettings from Moonraker's database namespace `fluidd`).
import Vue from 'vue'
import Vuex from 'vuex'
import { getters as printerGetters } from '@/store/printer/getters'
import { mutations as printerMutations } from '@/store/printer/mutations'
import { defaultState as printerDefaultState } from '@/store/printer/state'
import { getters as filesGetters } from '@/store/files/getters'
import { mutations as filesMutations } from '@/store/files/mutations'
import { defaultState as filesDefaultState } from '@/store/files/state'
import { getters as historyGetters } from '@/store/history/getters'
import { mutations as historyMutations } from '@/store/history/mutations'
import { defaultState as historyDefaultState } from '@/store/history/state'
import { mutations as configMutations } from '@/store/config/mutations'
import { defaultState as configDefaultState } from '@/store/config/state'
import getFilePaths from '@/util/get-file-paths'
import stringFormatters from '@/util/string-formatters'
import dateTimeFormatters from '@/util/date-time-formatters'

Vue.config.productionTip = false
Vue.config.devtools = false
Vue.use(Vuex)
// Fluidd's filters plugin (src/plugins/filters.ts) sets Vue.$filters from these two utilities
// (plus router and store helpers); the files and history getters call getStringArray and
// moonrakerDateAsUnixTime on them.  The plugin itself needs the whole app (router, store).
Vue.$filters = { ...stringFormatters(), ...dateTimeFormatters(() => 'iso', () => 'iso') }

export const GETTERS = [
  'getPrintProgress',
  'getFileRelativePrintProgress',
  'getFileAbsolutePrintProgress',
  'getSlicerPrintProgress',
  'getFilamentPrintProgress',
  'getTimeEstimates'
]

export function createStore (database, metadata, jobs) {
  const store = new Vuex.Store({
    modules: {
      printer: { namespaced: true, state: printerDefaultState(), getters: printerGetters, mutations: printerMutations },
      files: { namespaced: true, state: filesDefaultState(), getters: filesGetters, mutations: filesMutations },
      history: { namespaced: true, state: historyDefaultState(), getters: historyGetters, mutations: historyMutations },
      config: { namespaced: true, state: configDefaultState(), mutations: configMutations }
    }
  })
  // config/initUiSettings: the namespace's `uiSettings` root from server.database.get_item.
  if (database.uiSettings) store.commit('config/setInitUiSettings', database.uiSettings)
  // files/onFileMetaData: server.files.metadata's answer, its filename cut to the base name.
  if (metadata) {
    const paths = getFilePaths(metadata.filename, 'gcodes')
    store.commit('files/setFileUpdate', { paths, file: { ...metadata, filename: paths.filename } })
  }
  if (jobs && jobs.length) store.commit('history/setHistoryList', { jobs, count: jobs.length })
  return store
}

// printer/onNotifyStatusUpdate: each object committed with setSocketNotify.
export function feed (store, status) {
  for (const key in status) store.commit('printer/setSocketNotify', { key, payload: status[key] })
}

export function read (store) {
  const out = {}
  for (const name of GETTERS) out[name] = store.getters['printer/' + name]
  return out
}
